"""A linear Delta: the second mechanism behind the :class:`calib.mechanism.Mechanism` seam.

Three vertical linear actuators (columns) stand around the z axis of the base frame; column i carries a carriage at
height ``q_i + z0_i`` whose joint is at ``A_i = (R_i cos theta_i, R_i sin theta_i, q_i + z0_i)``; a parallelogram
leg of length ``L_i`` joins it to the plate's joint ``B_i = P + r (cos phi_i, sin phi_i, 0)``. The plate translates
only: the pose is its centre ``P = (x, y, z)`` (metres, base frame), which is also the point a camera observes (a
target at the plate's centre). The plate hangs below the carriages (``z < q_i + z0_i``).

Parameters (13, metres and radians): column radii ``R1..R3``, column angles ``theta1..theta3``, leg lengths
``L1..L3``, actuator zero offsets ``z01..z03`` and the plate radius ``r``. The plate's joint angles ``phi_i`` are
design constants (120 degrees apart), not parameters.

Identifiability from end-effector positions in the base frame: a leg only sees its column's horizontal position
relative to the plate's joint, ``c_i = R_i u(theta_i) - r u(phi_i)`` (``u(a) = (cos a, sin a)``). Twelve
combinations are identifiable, ``L_i``, ``z0_i``, ``cx_i``, ``cy_i``; the one unidentifiable direction (13 - 12) is
the plate radius traded against the columns: ``r -> r + e`` with each ``R_i u(theta_i)`` moved by
``e u(phi_i)`` (at ``theta_i = phi_i``: ``R_i -> R_i + e``, every ``R_i`` and ``r`` together).

Closed forms: the IKM per leg, ``q_i = z - z0_i + sqrt(L_i^2 - |(x, y) - c_i|^2)``; the DKM by the intersection of
the three spheres of centres ``(c_i, q_i + z0_i)`` and radii ``L_i`` (the lower of the two points); the Jacobian
``d q / d P`` row i ``(-(x - cx_i) / h_i, -(y - cy_i) / h_i, 1)`` with ``h_i = sqrt(L_i^2 - |(x, y) - c_i|^2)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from ..errors import UnreachableError
from ..mechanism import Array, as_rows

#: The plate's joint angles (design constants) and the nominal column angles: 90, 210, 330 degrees.
#: (three values: the declared 3-tuple, which mypy cannot count in a generator)
DESIGN_ANGLES: tuple[float, float, float] = tuple(math.pi / 2 + 2 * math.pi * i / 3 for i in range(3))  # type: ignore[assignment]

PARAMETER_NAMES: tuple[str, ...] = (
    "R1",
    "R2",
    "R3",
    "theta1",
    "theta2",
    "theta3",
    "L1",
    "L2",
    "L3",
    "z01",
    "z02",
    "z03",
    "r",
)
COMBINATION_NAMES: tuple[str, ...] = (
    "L1",
    "L2",
    "L3",
    "z01",
    "z02",
    "z03",
    "cx1",
    "cy1",
    "cx2",
    "cy2",
    "cx3",
    "cy3",
)
#: Smallest vertical extent of a leg, ``h_i`` (m), below which a pose is refused (near the singularity where a leg
#: lies flat, the DKM loses its accuracy).
MIN_LEG_HEIGHT_M = 0.02


def _triple(name: str, v: Any) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.size != 3 or not np.isfinite(a).all():
        raise ValueError(f"LinearDeltaParameters.{name} needs three finite values, got {v!r}")
    return float(a[0]), float(a[1]), float(a[2])


@dataclass(frozen=True)
class LinearDeltaParameters:
    """Geometry of a linear Delta (metres, radians).

    Parameters
    ----------
    R : tuple of 3 float
        Column radii: horizontal distance of the carriage joints from the base z axis.
    theta : tuple of 3 float
        Column angles about z (radians).
    L : tuple of 3 float
        Leg lengths (joint centre to joint centre).
    z0 : tuple of 3 float
        Actuator zero offsets: the carriage joint is at height ``q_i + z0_i``.
    r : float
        Plate radius: horizontal distance of the plate's joints from its centre.
    phi : tuple of 3 float
        The plate's joint angles (radians): design constants, not identified.
    """

    R: tuple[float, float, float] = (0.20, 0.20, 0.20)
    theta: tuple[float, float, float] = DESIGN_ANGLES
    L: tuple[float, float, float] = (0.30, 0.30, 0.30)
    z0: tuple[float, float, float] = (-0.50, -0.50, -0.50)
    r: float = 0.05
    phi: tuple[float, float, float] = field(default=DESIGN_ANGLES)

    def __post_init__(self) -> None:
        for name in ("R", "theta", "L", "z0", "phi"):
            object.__setattr__(self, name, _triple(name, getattr(self, name)))
        r = float(self.r)
        if not math.isfinite(r):
            raise ValueError(f"LinearDeltaParameters.r must be finite, got {self.r!r}")
        object.__setattr__(self, "r", r)
        if min(self.L) <= 0:
            raise ValueError(f"LinearDeltaParameters.L must be positive, got {self.L}")

    def vector(self) -> Array:
        """The 13 parameters in :data:`PARAMETER_NAMES` order."""
        return np.array([*self.R, *self.theta, *self.L, *self.z0, self.r], dtype=np.float64)

    @classmethod
    def from_vector(cls, values: ArrayLike, phi: tuple[float, float, float] = DESIGN_ANGLES) -> LinearDeltaParameters:
        """Build from 13 values in :data:`PARAMETER_NAMES` order."""
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.size != len(PARAMETER_NAMES):
            raise ValueError(f"LinearDeltaParameters.from_vector needs {len(PARAMETER_NAMES)} values, got {v.size}")
        # the slices are arrays of three: __post_init__ makes each field its 3-tuple of floats (_triple)
        return cls(R=v[0:3], theta=v[3:6], L=v[6:9], z0=v[9:12], r=v[12], phi=phi)  # type: ignore[arg-type]

    @cached_property
    def _columns(self) -> Array:
        R, th, ph = np.asarray(self.R), np.asarray(self.theta), np.asarray(self.phi)
        c = np.stack([R * np.cos(th) - self.r * np.cos(ph), R * np.sin(th) - self.r * np.sin(ph)], axis=1)
        c.flags.writeable = False
        return c

    def columns(self) -> Array:
        """Effective column positions ``c_i = R_i u(theta_i) - r u(phi_i)``, shape (3, 2), metres (read-only)."""
        return self._columns

    def replace(self, **changes: Any) -> LinearDeltaParameters:
        """A copy with some fields changed."""
        return replace(self, **changes)


NOMINAL = LinearDeltaParameters()


@dataclass(frozen=True)
class DeltaWorkspace:
    """Poses used to draw plans: a vertical cylinder (metres)."""

    radius: float = 0.12
    z: tuple[float, float] = (-0.45, -0.25)

    def grid(self, n_radial: int = 3, n_angle: int = 6, n_z: int = 3) -> Array:
        """A deterministic pose set: the axis and ``n_angle`` directions on ``n_radial - 1`` rings, at ``n_z``
        heights, shape ``(n_z * (1 + (n_radial - 1) * n_angle), 3)``."""
        rows = []
        for z in np.linspace(*self.z, n_z):
            rows.append([0.0, 0.0, z])
            for k in range(1, n_radial):
                rho = self.radius * k / (n_radial - 1)
                for a in np.arange(n_angle) * 2 * np.pi / n_angle + 0.3 * k:
                    rows.append([rho * np.cos(a), rho * np.sin(a), z])
        return np.array(rows, dtype=np.float64)

    def sample(self, n: int, rng: np.random.Generator) -> Array:
        """``n`` poses drawn uniformly in the cylinder, shape (n, 3)."""
        rho = self.radius * np.sqrt(rng.uniform(0, 1, n))
        a = rng.uniform(0, 2 * np.pi, n)
        z = rng.uniform(*self.z, n)
        return np.stack([rho * np.cos(a), rho * np.sin(a), z], axis=1)


class LinearDelta:
    """The linear Delta as a :class:`calib.mechanism.Mechanism` (module docstring for the model)."""

    name = "linear-delta"
    n_joints = 3
    pose_dim = 3
    parameter_names: tuple[str, ...] = PARAMETER_NAMES
    combination_names: tuple[str, ...] = COMBINATION_NAMES

    def nominal(self) -> LinearDeltaParameters:
        """:data:`NOMINAL`: R = 0.2 m, r = 0.05 m, L = 0.3 m, z0 = -0.5 m, columns at 90/210/330 degrees."""
        return NOMINAL

    def to_vector(self, params: LinearDeltaParameters) -> Array:
        """Shape (13,), metres and radians."""
        return params.vector()

    def from_vector(self, values: ArrayLike, reference: LinearDeltaParameters | None = None) -> LinearDeltaParameters:
        """13 values -> parameters; the design angles ``phi`` from ``reference`` (default :data:`NOMINAL`)."""
        ref = reference if reference is not None else NOMINAL
        return LinearDeltaParameters.from_vector(values, phi=ref.phi)

    # -- kinematics ------------------------------------------------------------------------------------------------
    def _heights(self, params: LinearDeltaParameters, P: Array) -> Array:
        """``h_i = sqrt(L_i^2 - d_i^2)``, shape (N, 3); raises for a leg that cannot reach."""
        c = params.columns()
        d2 = (P[:, None, 0] - c[None, :, 0]) ** 2 + (P[:, None, 1] - c[None, :, 1]) ** 2
        L = np.asarray(params.L)
        h2 = L**2 - d2
        bad = np.argwhere(h2 < MIN_LEG_HEIGHT_M**2)
        if bad.size:
            i, leg = int(bad[0, 0]), int(bad[0, 1])
            d = float(np.sqrt(d2[i, leg]))
            need = math.sqrt(d**2 + MIN_LEG_HEIGHT_M**2) - L[leg]
            more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
            raise UnreachableError(
                f"pose #{i} {np.round(P[i] * 1e3, 3).tolist()} mm is unreachable: leg {leg + 1} "
                f"(L = {L[leg] * 1e3:.3f} mm) reaches {d * 1e3:.3f} mm horizontally, {need * 1e3:.3f} mm too short "
                f"to keep {MIN_LEG_HEIGHT_M * 1e3:.0f} mm of height{more}",
                leg=leg + 1,
                index=i,
                deficit_m=need,
            )
        return np.sqrt(h2)

    def ikm(self, params: LinearDeltaParameters, pose: ArrayLike) -> Array:
        """Inverse kinematic model (closed form).

        Parameters
        ----------
        params : LinearDeltaParameters
        pose : array_like, shape (3,) or (N, 3)
            Plate centre ``(x, y, z)``, metres.

        Returns
        -------
        ndarray, shape (3,) or (N, 3)
            ``(q1, q2, q3)``, metres.

        Raises
        ------
        UnreachableError
            A leg cannot reach the pose (names the pose, the leg and by how much it is too short).
        """
        P, single = as_rows(pose, 3, "pose")
        h = self._heights(params, P)
        q = P[:, 2:3] - np.asarray(params.z0)[None, :] + h
        return q[0] if single else q

    def dkm(self, params: LinearDeltaParameters, q: ArrayLike) -> Array:
        """Direct kinematic model: the lower intersection of the three legs' spheres (closed form).

        Parameters
        ----------
        params : LinearDeltaParameters
        q : array_like, shape (3,) or (N, 3)
            Joint values, metres.

        Returns
        -------
        ndarray, shape (3,) or (N, 3)
            Plate centre ``(x, y, z)``, metres.

        Raises
        ------
        UnreachableError
            The three legs cannot meet (names the joint vector and by how much), or the pose they meet at leaves a
            leg flatter than :data:`MIN_LEG_HEIGHT_M`.
        """
        Q, single = as_rows(q, 3, "q")
        c = params.columns()
        L2 = np.square(params.L)
        Zc = Q + np.asarray(params.z0)  # carriage heights (N, 3); sphere centres (c_i, Zc_i), radii L_i
        n_rows = len(Q)
        a1 = np.empty((n_rows, 3))
        a2 = np.empty((n_rows, 3))
        a1[:, :2] = c[1] - c[0]
        a2[:, :2] = c[2] - c[0]
        a1[:, 2] = Zc[:, 1] - Zc[:, 0]
        a2[:, 2] = Zc[:, 2] - Zc[:, 0]
        # u = P - S0: a_k . u = (|a_k|^2 - L_k^2 + L_0^2) / 2, |u| = L_0; u = mu1 a1 + mu2 a2 + t n
        g11 = (a1 * a1).sum(axis=1)
        g12 = (a1 * a2).sum(axis=1)
        g22 = (a2 * a2).sum(axis=1)
        e1 = 0.5 * (g11 - L2[1] + L2[0])
        e2 = 0.5 * (g22 - L2[2] + L2[0])
        det = g11 * g22 - g12**2
        mu1 = (g22 * e1 - g12 * e2) / det
        mu2 = (g11 * e2 - g12 * e1) / det
        u0 = mu1[:, None] * a1 + mu2[:, None] * a2
        n = np.stack(
            [
                a1[:, 1] * a2[:, 2] - a1[:, 2] * a2[:, 1],
                a1[:, 2] * a2[:, 0] - a1[:, 0] * a2[:, 2],
                a1[:, 0] * a2[:, 1] - a1[:, 1] * a2[:, 0],
            ],
            axis=1,
        )
        n /= np.sqrt((n * n).sum(axis=1))[:, None]
        t2 = L2[0] - (u0 * u0).sum(axis=1)
        bad = np.flatnonzero(t2 < 0)
        if bad.size:
            i = int(bad[0])
            L0 = float(params.L[0])
            gap = float(np.sqrt(-t2[i] + L0**2) - L0)
            more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
            raise UnreachableError(
                f"joint vector #{i} {np.round(Q[i] * 1e3, 3).tolist()} mm is unreachable: the three legs cannot meet "
                f"(leg 1 is {gap * 1e3:.3f} mm too short to reach the other two's circle){more}",
                leg=1,
                index=i,
                deficit_m=gap,
            )
        t = -np.sign(n[:, 2]) * np.sqrt(t2)  # the lower of the two points
        P = u0 + t[:, None] * n
        P[:, :2] += c[0]
        P[:, 2] += Zc[:, 0]
        self._heights(params, P)  # a leg nearly flat: refused as by the IKM
        return P[0] if single else P

    def jacobian(self, params: LinearDeltaParameters, pose: ArrayLike) -> Array:
        """Jacobian of the inverse kinematic model, ``d q / d P`` (``q_dot = J P_dot``), analytic.

        Returns
        -------
        ndarray, shape (3, 3) or (N, 3, 3)
            Rows are legs, columns ``(x, y, z)``; dimensionless (m/m).
        """
        P, single = as_rows(pose, 3, "pose")
        h = self._heights(params, P)
        c = params.columns()
        J = np.empty((len(P), 3, 3))
        J[:, :, 0] = -(P[:, None, 0] - c[None, :, 0]) / h
        J[:, :, 1] = -(P[:, None, 1] - c[None, :, 1]) / h
        J[:, :, 2] = 1.0
        return J[0] if single else J

    def ee_parameter_jacobian(self, params: LinearDeltaParameters, q: ArrayLike) -> Array:
        """Identification Jacobian, analytic: ``d ee_point(dkm(params, q)) / d params`` at fixed joint values.

        By implicit differentiation of the leg closures ``f_i = |P_xy - c_i|^2 + (P_z - q_i - z0_i)^2 - L_i^2 = 0``:
        ``dP/dv = -(df/dP)^-1 df/dv``. Optional member of the seam (the generic fit differentiates numerically
        when a mechanism lacks it).

        Parameters
        ----------
        params : LinearDeltaParameters
        q : array_like, shape (N, 3)
            Joint values, metres.

        Returns
        -------
        ndarray, shape (N, 3, 13)
            Columns in :data:`PARAMETER_NAMES` order: m/m for lengths, m/rad for the angles.
        """
        Q, _ = as_rows(q, 3, "q")
        P = self.dkm(params, Q)
        c = params.columns()
        n = len(Q)
        w = P[:, None, :2] - c[None]  # (N, 3, 2)
        h = P[:, 2:3] - Q - np.asarray(params.z0)  # (N, 3)
        A = np.concatenate([w, h[:, :, None]], axis=2)  # df/dP / 2, (N, 3, 3)
        th, ph, R = np.asarray(params.theta), np.asarray(params.phi), np.asarray(params.R)
        u = np.stack([np.cos(th), np.sin(th)], axis=1)  # (3, 2)
        du = np.stack([-np.sin(th), np.cos(th)], axis=1)
        uphi = np.stack([np.cos(ph), np.sin(ph)], axis=1)
        F = np.zeros((n, 3, 13))  # df/dv / 2
        idx = np.arange(3)
        F[:, idx, idx] = -(w * u[None]).sum(axis=2)
        F[:, idx, 3 + idx] = -R[None] * (w * du[None]).sum(axis=2)
        F[:, idx, 6 + idx] = -np.asarray(params.L)[None]
        F[:, idx, 9 + idx] = -h
        F[:, :, 12] = (w * uphi[None]).sum(axis=2)
        return -np.linalg.solve(A, F)

    def ee_point(self, params: LinearDeltaParameters, pose: ArrayLike) -> Array:
        """The observed target: the plate's centre, the pose itself, shape (3,) or (N, 3), metres."""
        P, single = as_rows(pose, 3, "pose")
        return P[0] if single else P

    def identifiable_combinations(self, params: LinearDeltaParameters) -> dict[str, float]:
        """``L_i``, ``z0_i`` and the effective column positions ``(cx_i, cy_i)`` (metres), :data:`COMBINATION_NAMES`."""
        c = params.columns()
        out = {f"L{i + 1}": params.L[i] for i in range(3)}
        out.update({f"z0{i + 1}": params.z0[i] for i in range(3)})
        for i in range(3):
            out[f"cx{i + 1}"] = float(c[i, 0])
            out[f"cy{i + 1}"] = float(c[i, 1])
        return out

    def leg_rods(self, params: LinearDeltaParameters, q: ArrayLike, pose: ArrayLike) -> tuple[Array, Array]:
        """Carriage joints ``A_i`` and plate joints ``B_i`` (the parallelograms' equivalent legs).

        Returns
        -------
        A, B : ndarray, shape (N, 3, 3)
            Metres, base frame.
        """
        Q, _ = as_rows(q, 3, "q")
        P, _ = as_rows(pose, 3, "pose")
        R, th, ph = np.asarray(params.R), np.asarray(params.theta), np.asarray(params.phi)
        A = np.empty((len(Q), 3, 3))
        A[:, :, 0] = R * np.cos(th)
        A[:, :, 1] = R * np.sin(th)
        A[:, :, 2] = Q + np.asarray(params.z0)
        B = P[:, None, :] + params.r * np.stack([np.cos(ph), np.sin(ph), np.zeros(3)], axis=1)[None]
        return A, B

    def __repr__(self) -> str:
        return "LinearDelta()"


if TYPE_CHECKING:  # mypy checks that the class satisfies the protocol
    from ..mechanism import Mechanism

    _protocol_check: Mechanism = LinearDelta()

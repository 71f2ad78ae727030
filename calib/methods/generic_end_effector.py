"""End-effector identification for any :class:`calib.mechanism.Mechanism`.

Given joint readings ``q`` (N, n_joints) and measured end-effector points (N, 3) in the base frame with their
standard deviations, fit the mechanism's parameters by weighted least squares (``scipy.optimize.least_squares``)
through its direct kinematic model and :meth:`~calib.mechanism.Mechanism.ee_point`:

``r_k = (ee_point(dkm(p, q_k)) - y_k) / sigma_k``.

Unidentifiable directions. The identification Jacobian at the start point (columns scaled to unit norm) is
decomposed by SVD; directions whose singular value is below ``rank_rtol`` times the largest one are the
unidentifiable ones (e.g. the linear Delta's plate radius traded against its column radii): the fit moves only in
the subspace orthogonal to them (in the column-scaled coordinates), so the estimate has no component along them
relative to the start point (a minimum-norm update; a parameter such as the Delta's ``r`` may still move, within
that subspace). The Jacobian is the mechanism's ``ee_parameter_jacobian(params, q)`` (shape (N, 3, p)) when it
has one, else central differences. The covariance of the
parameters is that of the estimate in this gauge; a parameter that has a component along an unidentifiable
direction has no standard deviation of its own (NaN, ``identifiable[name] = False``), while every combination that
the mechanism declares identifiable (:meth:`~calib.mechanism.Mechanism.identifiable_combinations`) has one, by
first-order propagation.

Covariance: ``s^2 (J^T J)^-1`` with ``J`` the whitened Jacobian at the solution and ``s^2 = chi^2 / dof`` (the
residuals' scale; ``scale_by_residuals=False``: ``s = 1``, the given standard deviations taken as exact).

This is a method of its own: the I4's methods (:mod:`calib.methods.end_effector`, which also estimates the camera
and board placements) are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from ..errors import ConvergenceError, IdentifiabilityError, InputError, UnreachableError
from ..mechanism import Mechanism, as_rows
from ..numdiff import central_jacobian

Array = NDArray[np.float64]

#: Whitened residual used for a trial point at which the DKM fails (the trust region then shrinks).
_UNREACHABLE_RESIDUAL = 1e6


@dataclass(frozen=True)
class GenericEndEffectorResult:
    """What :func:`fit_end_effector` found.

    Attributes
    ----------
    mechanism : str
        The mechanism's registry name.
    estimate : object
        The fitted geometry (the mechanism's parameter object).
    parameters, std : dict of str to float
        Every parameter (metres, radians) and its standard deviation; NaN where the parameter is not identifiable
        on its own.
    identifiable : dict of str to bool
        Whether each parameter is identifiable on its own from these data.
    covariance : ndarray, shape (p, p)
        Of the parameter vector in the fit's gauge (singular along the unidentifiable directions).
    combinations, combinations_std : dict of str to float
        The mechanism's identifiable combinations and their standard deviations.
    combinations_covariance : ndarray, shape (c, c)
    rank : int
        Number of identifiable directions found.
    null_directions : list of dict of str to float
        Each unidentifiable direction as a unit vector over the parameters (components below 1e-6 left out).
    sigma0 : float
        ``sqrt(chi2 / dof)``: 1 when the given standard deviations are right.
    chi2 : float
        Sum of squared whitened residuals.
    dof : int
        ``3 N - rank``.
    residuals_m : ndarray, shape (N, 3)
        Fitted minus measured points, metres.
    nfev : int
        Residual evaluations of the optimiser.
    """

    mechanism: str
    estimate: Any
    parameters: dict[str, float]
    std: dict[str, float]
    identifiable: dict[str, bool]
    covariance: Array
    combinations: dict[str, float]
    combinations_std: dict[str, float]
    combinations_covariance: Array
    rank: int
    null_directions: list[dict[str, float]]
    sigma0: float
    chi2: float
    dof: int
    residuals_m: Array = field(repr=False)
    nfev: int = 0
    converged: bool = True

    def summary(self) -> dict[str, Any]:
        """JSON-able summary (metres, radians)."""
        return {
            "mechanism": self.mechanism,
            "parameters": self.parameters,
            "std": {k: (None if not np.isfinite(v) else v) for k, v in self.std.items()},
            "identifiable": self.identifiable,
            "combinations": self.combinations,
            "combinations_std": self.combinations_std,
            "rank": self.rank,
            "null_directions": self.null_directions,
            "sigma0": self.sigma0,
            "dof": self.dof,
            "converged": self.converged,
        }


def fit_end_effector(
    mechanism: Mechanism,
    q: ArrayLike,
    points: ArrayLike,
    std: ArrayLike,
    *,
    initial: Any | None = None,
    scale_by_residuals: bool = True,
    rank_rtol: float = 1e-7,
    max_nfev: int = 200,
) -> GenericEndEffectorResult:
    """Identify ``mechanism``'s parameters from joint readings and measured end-effector points.

    Parameters
    ----------
    mechanism : Mechanism
    q : array_like, shape (N, n_joints)
        Joint readings (encoders), metres.
    points : array_like, shape (N, 3)
        Measured end-effector points in the base frame, metres.
    std : array_like, scalar, shape (3,) or (N, 3)
        Standard deviations of ``points``, metres (> 0).
    initial : object, optional
        Start geometry (default: ``mechanism.nominal()``); the unidentifiable directions stay at its values.
    scale_by_residuals : bool
        Scale the covariance by ``chi2 / dof``.
    rank_rtol : float
        Relative singular-value threshold of the identifiable directions (column-scaled Jacobian).
    max_nfev : int
        Bound on the optimiser's residual evaluations.

    Returns
    -------
    GenericEndEffectorResult

    Raises
    ------
    InputError
        Shapes that do not match, non-finite values, non-positive standard deviations.
    UnreachableError
        The start geometry cannot assemble at some joint reading (names the row).
    IdentifiabilityError
        Fewer measurements than identifiable directions.
    ConvergenceError
        The optimiser stopped at ``max_nfev`` or failed.
    """
    Q, _ = as_rows(q, mechanism.n_joints, "q")
    Y, _ = as_rows(points, 3, "points")
    if len(Q) != len(Y):
        raise InputError(f"{len(Q)} joint readings but {len(Y)} measured points", field="points")
    S = np.broadcast_to(np.asarray(std, dtype=np.float64), Y.shape).copy()
    if not np.all(np.isfinite(S) & (S > 0)):
        raise InputError("standard deviations must be finite and positive", field="std")
    p0 = initial if initial is not None else mechanism.nominal()
    v0 = mechanism.to_vector(p0)
    names = mechanism.parameter_names

    def residual_v(v: Array) -> Array:
        p = mechanism.from_vector(v, reference=p0)
        return ((mechanism.ee_point(p, mechanism.dkm(p, Q)) - Y) / S).ravel()

    analytic = getattr(mechanism, "ee_parameter_jacobian", None)

    def jacobian_v(v: Array) -> Array:
        if analytic is None:
            return central_jacobian(residual_v, v)
        p = mechanism.from_vector(v, reference=p0)
        return (np.asarray(analytic(p, Q)) / S[:, :, None]).reshape(Y.size, v.size)

    residual_v(v0)  # UnreachableError here names the joint reading the start geometry cannot assemble
    J0 = jacobian_v(v0)
    col = np.linalg.norm(J0, axis=0)
    D = np.where(col > 0, 1.0 / np.where(col > 0, col, 1.0), 0.0)
    _, s, Vt = np.linalg.svd(J0 * D, full_matrices=False)
    rank = int(np.sum(s > rank_rtol * s[0])) if s.size and s[0] > 0 else 0
    if rank == 0 or Y.size <= rank:
        raise IdentifiabilityError(
            f"{mechanism.name}: {Y.size} measured coordinates for {rank} identifiable directions; more poses needed"
        )
    B = D[:, None] * Vt[:rank].T  # v = v0 + B alpha

    def residual(alpha: Array) -> Array:
        try:
            return residual_v(v0 + B @ alpha)
        except UnreachableError:
            return np.full(Y.size, _UNREACHABLE_RESIDUAL)

    def jac(alpha: Array) -> Array:
        try:
            return jacobian_v(v0 + B @ alpha) @ B
        except UnreachableError:
            return J0 @ B

    sol = least_squares(residual, np.zeros(rank), jac=jac, method="trf", x_scale="jac", max_nfev=max_nfev)
    if sol.status <= 0:
        raise ConvergenceError(f"{mechanism.name} end-effector fit did not converge: {sol.message} ({sol.nfev} evals)")
    v_hat = v0 + B @ sol.x
    r = residual_v(v_hat)
    chi2 = float(r @ r)
    dof = Y.size - rank
    s2 = chi2 / dof if scale_by_residuals else 1.0
    J_hat = jacobian_v(v_hat)
    J = J_hat @ B
    cov_a = s2 * np.linalg.inv(J.T @ J)
    cov_v = B @ cov_a @ B.T
    est = mechanism.from_vector(v_hat, reference=p0)

    # what these data leave unidentified, at the estimate (the fit's subspace was chosen at the start point)
    rank_hat, null_unit = _null_directions(J_hat, rank_rtol)
    ident = {n: bool(np.all(np.abs(null_unit[k]) < 1e-6)) for k, n in enumerate(names)}
    std_v = np.sqrt(np.clip(np.diag(cov_v), 0.0, None))
    comb_names = mechanism.combination_names

    def combos(v: Array) -> Array:
        c = mechanism.identifiable_combinations(mechanism.from_vector(v, reference=p0))
        return np.array([c[n] for n in comb_names], dtype=np.float64)

    Jc = central_jacobian(combos, v_hat)
    cov_c = Jc @ cov_v @ Jc.T
    c_hat = combos(v_hat)
    return GenericEndEffectorResult(
        mechanism=mechanism.name,
        estimate=est,
        parameters={n: float(v_hat[k]) for k, n in enumerate(names)},
        std={n: (float(std_v[k]) if ident[n] else float("nan")) for k, n in enumerate(names)},
        identifiable=ident,
        covariance=cov_v,
        combinations={n: float(c_hat[k]) for k, n in enumerate(comb_names)},
        combinations_std={n: float(np.sqrt(max(cov_c[k, k], 0.0))) for k, n in enumerate(comb_names)},
        combinations_covariance=cov_c,
        rank=rank_hat,
        null_directions=[
            {n: float(round(null_unit[k, j], 9)) for k, n in enumerate(names) if abs(null_unit[k, j]) > 1e-6}
            for j in range(null_unit.shape[1])
        ],
        sigma0=float(np.sqrt(chi2 / dof)),
        chi2=chi2,
        dof=dof,
        residuals_m=(r * S.ravel()).reshape(Y.shape),
        nfev=int(sol.nfev),
        converged=True,
    )


def _null_directions(J: Array, rank_rtol: float) -> tuple[int, Array]:
    """The rank of the column-scaled Jacobian ``J`` (M, P) and its null directions as unit columns (P, P - rank), each
    signed so that its largest component is positive."""
    col = np.linalg.norm(J, axis=0)
    D = np.where(col > 0, 1.0 / np.where(col > 0, col, 1.0), 0.0)
    _, s, Vt = np.linalg.svd(J * D, full_matrices=False)
    rank = int(np.sum(s > rank_rtol * s[0]))
    null = D[:, None] * Vt[rank:].T
    norms = np.linalg.norm(null, axis=0)
    null_unit = null / np.where(norms > 0, norms, 1.0)
    for j in range(null_unit.shape[1]):  # sign: largest component positive
        if null_unit[np.argmax(np.abs(null_unit[:, j])), j] < 0:
            null_unit[:, j] *= -1
    return rank, null_unit


__all__ = ["GenericEndEffectorResult", "fit_end_effector"]

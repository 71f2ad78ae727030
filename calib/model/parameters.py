"""The seven geometric parameters of the I4 mechanism and their identifiable combinations."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np

#: Names of the seven geometric parameters, in the paper's order.
PARAMETER_NAMES: tuple[str, ...] = ("H", "q02", "q03", "q04", "S", "D", "L")
#: Names of the four combinations that Jacobian-based and IKM-based methods identify.
COMBINATION_NAMES: tuple[str, ...] = ("L", "H-D", "S-q02/2", "S-(q04-q03)/2")

#: The four combinations as linear functions of the seven parameters, (4, 7): rows COMBINATION_NAMES, columns
#: PARAMETER_NAMES (a covariance of the seven maps to the four's as ``SEVEN_TO_FOUR @ cov7 @ SEVEN_TO_FOUR.T``).
SEVEN_TO_FOUR = np.array(
    [
        [0, 0, 0, 0, 0, 0, 1],  # L
        [1, 0, 0, 0, 0, -1, 0],  # H - D
        [0, -0.5, 0, 0, 1, 0, 0],  # S - q02/2
        [0, 0, 0.5, -0.5, 1, 0, 0],  # S - (q04 - q03)/2
    ],
    dtype=float,
)
SEVEN_TO_FOUR.flags.writeable = False

#: Default rack-and-pinion constant: metres of T per radian of end-effector rotation.
DEFAULT_T_PER_RAD = 0.02


@dataclass(frozen=True, slots=True)
class I4Parameters:
    """Geometry of an I4 mechanism, every length in metres.

    Parameters
    ----------
    H : float
        Half the distance between the two actuator axes (A1, A2 at y = 0; A3, A4 at y = 2H).
    q02, q03, q04 : float
        Encoder offsets: ``OA_i . x_B = q_i + q0i``.
    S, D : float
        Half-spacings of the lower joints B_i on the traveling plate along x_B and y_B.
    L : float
        Length of the (equivalent) legs.
    T_per_rad : float
        Rack-and-pinion constant, metres of T per radian of end-effector rotation about
        z_B (positive T turns it positively). Not one of the seven parameters: a constant
        of the model, never identified.
    """

    H: float
    q02: float
    q03: float
    q04: float
    S: float
    D: float
    L: float
    T_per_rad: float = DEFAULT_T_PER_RAD

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"I4Parameters.{f.name} must be a number, got {value!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"I4Parameters.{f.name} must be finite, got {value!r}")
            object.__setattr__(self, f.name, value)
        if self.L <= 0:
            raise ValueError(f"I4Parameters.L must be positive, got {self.L}")
        if self.H - self.D == 0:
            raise ValueError("I4Parameters: H - D must not be zero (the DKM divides by it)")
        if self.T_per_rad <= 0:
            raise ValueError(f"I4Parameters.T_per_rad must be positive, got {self.T_per_rad}")

    # -- views -----------------------------------------------------------------
    def seven(self) -> dict[str, float]:
        """The seven parameters as a name -> metres mapping."""
        return {n: getattr(self, n) for n in PARAMETER_NAMES}

    def as_dict(self) -> dict[str, float]:
        """All fields, including ``T_per_rad``."""
        return asdict(self)

    def vector(self) -> list[float]:
        """The seven parameters in :data:`PARAMETER_NAMES` order."""
        return [getattr(self, n) for n in PARAMETER_NAMES]

    def combinations(self) -> dict[str, float]:
        """The four identifiable combinations (see :func:`identifiable_parameters`)."""
        return identifiable_parameters(self)

    def replace(self, **changes: Any) -> I4Parameters:
        """A copy with some fields changed.

        Parameters
        ----------
        **changes : float
            New values of fields, by name (metres; ``T_per_rad`` in metres per radian).

        Returns
        -------
        I4Parameters
            The copy, validated.
        """
        return replace(self, **changes)

    @classmethod
    def from_vector(cls, values: Any, T_per_rad: float = DEFAULT_T_PER_RAD) -> I4Parameters:
        """Build from seven values in :data:`PARAMETER_NAMES` order.

        Parameters
        ----------
        values : iterable of float, length 7
            The seven parameters, metres.
        T_per_rad : float, optional
            Rack-and-pinion constant, metres per radian.

        Returns
        -------
        I4Parameters
            The geometry.

        Raises
        ------
        ValueError
            If there are not seven values, or a value is invalid.
        """
        vals = [float(v) for v in values]
        if len(vals) != 7:
            raise ValueError(f"I4Parameters.from_vector needs 7 values, got {len(vals)}")
        return cls(*vals, T_per_rad=T_per_rad)  # type: ignore[misc]  # mypy cannot count the starred values

    @classmethod
    def from_mapping(cls, data: dict[str, Any]) -> I4Parameters:
        """Build from a mapping with the seven names (and optionally ``T_per_rad``).

        Parameters
        ----------
        data : dict
            ``{name: metres}`` for the seven :data:`PARAMETER_NAMES`, optionally ``"T_per_rad"`` (metres per
            radian; None keeps the default). Other keys are ignored.

        Returns
        -------
        I4Parameters
            The geometry.

        Raises
        ------
        ValueError
            If a name is missing or a value is invalid.
        """
        missing = [n for n in PARAMETER_NAMES if n not in data]
        if missing:
            raise ValueError(f"missing parameter(s): {', '.join(missing)}")
        kw = {n: data[n] for n in PARAMETER_NAMES}
        if "T_per_rad" in data and data["T_per_rad"] is not None:
            kw["T_per_rad"] = data["T_per_rad"]
        return cls(**kw)

    @classmethod
    def from_combinations(cls, combos: dict[str, float], reference: I4Parameters) -> I4Parameters:
        """Complete four identified combinations into seven parameters.

        The parts no Jacobian- or IKM-based method sees (H, S, q03: constant offsets of X
        and T) are taken from ``reference``; D, q02 and q04 follow from the combinations.
        The result has exactly the given combinations and predicts the same displacements.

        Parameters
        ----------
        combos : dict
            The four combinations, ``{name: metres}`` keyed by :data:`COMBINATION_NAMES`.
        reference : I4Parameters
            Geometry giving H, S, q03 and ``T_per_rad``.

        Returns
        -------
        I4Parameters
            The completed geometry.
        """
        H, S, q03 = reference.H, reference.S, reference.q03
        return cls(
            H=H,
            q02=2.0 * (S - combos["S-q02/2"]),
            q03=q03,
            q04=q03 + 2.0 * (S - combos["S-(q04-q03)/2"]),
            S=S,
            D=H - combos["H-D"],
            L=combos["L"],
            T_per_rad=reference.T_per_rad,
        )


def identifiable_parameters(params: I4Parameters) -> dict[str, float]:
    """The four combinations identifiable by Jacobian- or IKM-based methods, in metres.

    Parameters
    ----------
    params : I4Parameters
        The geometry (metres).

    Returns
    -------
    dict
        ``{"L", "H-D", "S-q02/2", "S-(q04-q03)/2"}``. The paper's text writes
        ``E - (q04 - q02)/2``; its Table I and the model give ``S - (q04 - q03)/2``.
    """
    return {
        "L": params.L,
        "H-D": params.H - params.D,
        "S-q02/2": params.S - params.q02 / 2.0,
        "S-(q04-q03)/2": params.S - (params.q04 - params.q03) / 2.0,
    }


#: A priori geometry matching the paper's Table I combinations
#: (L = 1.001 m, H-D = 0.3464 m, S-q02/2 = -0.6316 m, S-(q04-q03)/2 = -0.6304 m).
NOMINAL = I4Parameters(H=0.40, q02=1.3832, q03=0.0, q04=1.3808, S=0.06, D=0.0536, L=1.001)

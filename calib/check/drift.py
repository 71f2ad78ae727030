"""Does a calibration still hold? A short check's estimate of the four combinations tested against the calibration
in force, and the update that the check's data propose where it drifted.

The check and the calibration in force are independent estimates of the same four combinations ``L``, ``H-D``,
``S-q02/2``, ``S-(q04-q03)/2`` (metres). Under the hypothesis that nothing moved, their difference ``d`` is
Gaussian with zero mean and covariance ``S = C_check + C_in_force``; each combination's standardised change
``z_i = d_i / sqrt(S_ii)`` is standard normal. The test rejects when the largest ``|z_i|`` passes the threshold
that gives a family-wise false-alarm probability ``alpha`` over the four combinations (computed exactly from the
correlation of ``z`` by the multivariate normal distribution, not by a Bonferroni bound), and names each
combination beyond it.

The update is a Kalman step: the calibration in force is the prior, with each drifted combination released (a
random-walk step of unknown size), so that the check's data decide it while the other combinations keep what the
full calibration knew. The update is refused when the check's estimate did not converge, or when the update and
either its prior or the check's data disagree beyond the test's threshold on a combination kept from the prior.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq
from scipy.stats import multivariate_normal, norm

from calib.errors import InputError
from calib.model.parameters import COMBINATION_NAMES, I4Parameters

if TYPE_CHECKING:
    from calib.identify.export import CalibrationDocument

Array = NDArray[np.float64]
Verdict = Literal["holds", "drifted", "inconclusive"]


@dataclass(frozen=True)
class CombinationEstimate:
    """An estimate of the four combinations.

    Attributes
    ----------
    value_m : ndarray, shape (4,)
        ``L, H-D, S-q02/2, S-(q04-q03)/2``, metres, in :data:`calib.model.parameters.COMBINATION_NAMES` order.
    covariance_m2 : ndarray, shape (4, 4)
        Their covariance, m^2.
    converged : bool
        Whether the fit that made it converged.
    """

    value_m: Array
    covariance_m2: Array
    converged: bool = True

    @classmethod
    def from_dicts(
        cls, values_m: dict[str, float], covariance_m2: list[list[float]] | Array, *, converged: bool = True
    ) -> CombinationEstimate:
        """From a result's ``combinations`` (name -> metres) and 4x4 ``covariance`` (m^2).

        Parameters
        ----------
        values_m : dict
            ``{name: metres}`` with the four :data:`~calib.model.parameters.COMBINATION_NAMES` (others ignored).
        covariance_m2 : array_like, shape (4, 4)
            Their covariance in that order, m^2.
        converged : bool, optional
            Whether the fit that made it converged.

        Returns
        -------
        CombinationEstimate
            The estimate.

        Raises
        ------
        InputError
            If a combination is missing (``field="combinations"``).
        """
        missing = [k for k in COMBINATION_NAMES if k not in values_m]
        if missing:
            raise InputError(f"missing combinations {missing}", field="combinations")
        return cls(
            np.array([float(values_m[k]) for k in COMBINATION_NAMES]),
            np.asarray(covariance_m2, dtype=np.float64),
            converged,
        )

    def std_m(self) -> Array:
        """Standard deviations, metres, shape (4,)."""
        return np.sqrt(np.clip(np.diag(self.covariance_m2), 0.0, None))


@dataclass(frozen=True)
class DriftSettings:
    """How the check decides.

    Attributes
    ----------
    alpha : float
        Family-wise false-alarm probability over the four combinations when nothing drifted.
    max_check_std_m : float
        A combination whose check std (m) is above this is not pinned by the check: the verdict is
        ``inconclusive`` for it unless another combination drifted.
    """

    alpha: float = 0.05
    max_check_std_m: float = 1e-3

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha < 0.5:
            raise InputError(f"alpha must lie in (0, 0.5), got {self.alpha}", field="alpha")
        if not self.max_check_std_m > 0.0:
            raise InputError(f"max_check_std_m must be positive, got {self.max_check_std_m}", field="max_check_std_m")


@dataclass(frozen=True)
class DriftResult:
    """The check's verdict.

    Attributes
    ----------
    verdict : {"holds", "drifted", "inconclusive"}
    change_m : dict
        Combination -> estimated change (check minus in force), metres.
    change_std_m : dict
        Combination -> its std, metres (check and calibration in force together).
    z : dict
        Combination -> the standardised change.
    threshold : float
        The ``|z|`` above which a combination counts as drifted.
    statistic : float
        The largest ``|z|`` (the test's statistic).
    drifted : tuple of str
        The combinations beyond the threshold.
    reasons : list of str
        What made the verdict inconclusive, in words.
    """

    verdict: Verdict
    change_m: dict[str, float]
    change_std_m: dict[str, float]
    z: dict[str, float]
    threshold: float
    statistic: float
    drifted: tuple[str, ...]
    reasons: list[str] = field(default_factory=list)


def max_abs_z_threshold(correlation: Array, alpha: float) -> float:
    """The threshold ``t`` with ``P(max_i |z_i| > t) = alpha`` for ``z ~ N(0, correlation)``.

    Parameters
    ----------
    correlation : ndarray, shape (k, k)
        Correlation matrix of ``z`` (unit diagonal).
    alpha : float
        Family-wise false-alarm probability.

    Returns
    -------
    float
        The threshold (between the one-sided-free single-test value and the Bonferroni value).
    """
    rounded = np.round(np.asarray(correlation, dtype=np.float64), 6)
    return _threshold(rounded.shape[0], tuple(rounded.ravel().tolist()), float(alpha))


@functools.lru_cache(maxsize=256)
def _threshold(k: int, correlation_flat: tuple[float, ...], alpha: float) -> float:
    """:func:`max_abs_z_threshold` for a correlation rounded to 1e-6 (cached: a check's covariances repeat)."""
    correlation = np.array(correlation_flat).reshape(k, k)
    lo = float(norm.isf(alpha / 2.0))
    hi = float(norm.isf(alpha / (2.0 * k)))
    if k == 1 or hi - lo < 1e-9:
        return hi
    mvn = multivariate_normal(mean=np.zeros(k), cov=correlation, allow_singular=True)

    def excess(t: float) -> float:
        inside = float(mvn.cdf(np.full(k, t), lower_limit=np.full(k, -t)))
        return (1.0 - inside) - alpha

    if excess(hi) >= 0.0:
        return hi
    if excess(lo) <= 0.0:
        return lo
    return float(brentq(excess, lo, hi, xtol=1e-6))


def _check_estimate(e: CombinationEstimate, name: str) -> None:
    if e.value_m.shape != (4,) or e.covariance_m2.shape != (4, 4):
        raise InputError("expected 4 combinations and a 4x4 covariance", field=name)
    if not (np.all(np.isfinite(e.value_m)) and np.all(np.isfinite(e.covariance_m2))):
        raise InputError("combinations and covariance must be finite", field=name)


def check_drift(
    in_force: CombinationEstimate, check: CombinationEstimate, settings: DriftSettings | None = None
) -> DriftResult:
    """Test the check's estimate against the calibration in force.

    Parameters
    ----------
    in_force : CombinationEstimate
        The calibration in force (its four combinations and covariance).
    check : CombinationEstimate
        The check's estimate from its own frames.
    settings : DriftSettings, optional

    Returns
    -------
    DriftResult
        ``drifted`` when a combination's standardised change passes the family-wise threshold (naming each one
        beyond it); ``inconclusive`` when the check did not converge, or pins no combination, or a combination it
        cannot pin left the rest consistent; else ``holds``.
    """
    settings = settings or DriftSettings()
    _check_estimate(in_force, "in_force")
    _check_estimate(check, "check")
    d = check.value_m - in_force.value_m
    S = 0.5 * (check.covariance_m2 + check.covariance_m2.T + in_force.covariance_m2 + in_force.covariance_m2.T)
    sd = np.sqrt(np.clip(np.diag(S), 0.0, None))
    pinned = check.std_m() <= settings.max_check_std_m
    ok = pinned & (sd > 0.0)
    z = np.where(ok, d / np.where(sd > 0.0, sd, 1.0), 0.0)
    names = COMBINATION_NAMES
    reasons: list[str] = []
    if not check.converged:
        reasons.append("the check's fit did not converge")
    unpinned = [n for n, p in zip(names, pinned, strict=True) if not p]
    if unpinned:
        reasons.append(
            f"the check does not pin {', '.join(unpinned)} (std above {settings.max_check_std_m * 1e3:g} mm)"
        )
    idx = np.flatnonzero(ok)
    threshold = float("inf")
    if idx.size:
        sub = S[np.ix_(idx, idx)] / np.outer(sd[idx], sd[idx])
        threshold = max_abs_z_threshold(sub, settings.alpha)
    statistic = float(np.max(np.abs(z[idx]))) if idx.size else 0.0
    drifted = tuple(n for n, zi, o in zip(names, z, ok, strict=True) if o and abs(zi) > threshold)
    verdict: Verdict
    if not check.converged or not idx.size:
        verdict = "inconclusive"
    elif drifted:
        verdict = "drifted"
    elif unpinned:
        verdict = "inconclusive"
    else:
        verdict = "holds"
    return DriftResult(
        verdict=verdict,
        change_m={n: float(v) for n, v in zip(names, d, strict=True)},
        change_std_m={n: float(v) for n, v in zip(names, sd, strict=True)},
        z={n: float(v) for n, v in zip(names, z, strict=True)},
        threshold=threshold,
        statistic=statistic,
        drifted=drifted,
        reasons=reasons,
    )


@dataclass(frozen=True)
class UpdateResult:
    """A proposed update of the calibration in force.

    Attributes
    ----------
    accepted : bool
        False: the update is refused (``reason`` says why) and must not be applied.
    estimate : CombinationEstimate
        The updated combinations and covariance (the calibration in force when refused).
    reestimated : tuple of str
        The combinations the check's data decide alone (those that drifted); the others keep the calibration in
        force as prior.
    reason : str
    """

    accepted: bool
    estimate: CombinationEstimate
    reestimated: tuple[str, ...] = ()
    reason: str = ""


def update_from_check(
    in_force: CombinationEstimate,
    check: CombinationEstimate,
    drift: DriftResult,
    settings: DriftSettings | None = None,
) -> UpdateResult:
    """The calibration re-estimated from the check with the calibration in force as prior.

    A Kalman step whose prior is the calibration in force with its drifted combinations released: the step of a
    random walk whose size is unknown, so the check's data decide them alone, while the combinations the test found
    unchanged keep their prior (marginal of the calibration in force's covariance). In covariance form, starting
    from the check ``(x_c, C)``, the prior on the unchanged set ``N`` is a measurement ``x_N = E_N x`` with noise
    ``P_NN``: ``K = C E_N^T (E_N C E_N^T + P_NN)^-1``, ``x = x_c + K (x_prior_N - E_N x_c)``, ``cov = (I - K E_N) C``.

    Parameters
    ----------
    in_force, check : CombinationEstimate
        As given to `check_drift`.
    drift : DriftResult
        `check_drift`'s result for the same pair.
    settings : DriftSettings, optional

    Returns
    -------
    UpdateResult
        Refused when the check did not converge, when nothing drifted (nothing to update), when the update moves
        a combination the check found unchanged beyond the test's threshold (it contradicts its prior), or when the
        check's data contradict a combination the update kept from the prior (residual ``x_c - x`` with variance
        ``C_ii - cov_ii``) beyond that threshold.
    """
    settings = settings or DriftSettings()
    if not check.converged:
        return UpdateResult(False, in_force, reason="the check's fit did not converge: nothing to update from")
    if drift.verdict != "drifted":
        return UpdateResult(False, in_force, reason=f"the verdict is {drift.verdict!r}: no update proposed")
    kept = np.array([n not in drift.drifted for n in COMBINATION_NAMES])
    C = 0.5 * (check.covariance_m2 + check.covariance_m2.T)
    value, cov = check.value_m.copy(), C
    if kept.any():
        E = np.eye(4)[kept]
        P_nn = in_force.covariance_m2[np.ix_(kept, kept)]
        gain = C @ E.T @ np.linalg.inv(E @ C @ E.T + P_nn)
        value = check.value_m + gain @ (in_force.value_m[kept] - E @ check.value_m)
        cov = (np.eye(4) - gain @ E) @ C
        cov = 0.5 * (cov + cov.T)
    updated = CombinationEstimate(value, cov, True)
    sd = np.array([drift.change_std_m[n] for n in COMBINATION_NAMES])
    moved = np.abs(value - in_force.value_m) / np.where(sd > 0.0, sd, np.inf)
    contradicted = [n for n, m, k in zip(COMBINATION_NAMES, moved, kept, strict=True) if k and m > drift.threshold]
    if contradicted:
        return UpdateResult(
            False,
            in_force,
            reason=f"the update moves {', '.join(contradicted)}, which the check found unchanged, beyond the test: "
            "run a full calibration",
        )
    resid_var = np.clip(np.diag(C) - np.diag(cov), 0.0, None)
    resid = np.abs(check.value_m - value) / np.where(resid_var > 0.0, np.sqrt(resid_var), np.inf)
    disagreed = [n for n, m, k in zip(COMBINATION_NAMES, resid, kept, strict=True) if k and m > drift.threshold]
    if disagreed:
        return UpdateResult(
            False,
            in_force,
            reason=f"the check's data contradict the update on {', '.join(disagreed)}, kept from the calibration in "
            "force, beyond the test: run a full calibration",
        )
    return UpdateResult(True, updated, tuple(drift.drifted))


#: the completion rule of an update's seven parameters (``completion.rule`` of its ``i4cal.calibration/1`` document)
UPDATE_COMPLETION_RULE = "combinations+in-force"
UPDATE_COMPLETION_TEXT = (
    "a check's update of the four combinations completed with the H, S, q03 of the calibration in force: "
    "q02 = 2 (S - (S-q02/2)), q04 = q03 + 2 (S - (S-(q04-q03)/2)), D = H - (H-D), L = L"
)


def in_force_estimate(doc: CalibrationDocument) -> CombinationEstimate:
    """The four combinations and covariance of an ``i4cal.calibration/1`` document, the check's prior.

    Parameters
    ----------
    doc : CalibrationDocument
        The calibration in force.

    Returns
    -------
    CombinationEstimate
        Its combinations (metres) and their 4x4 covariance (m^2), in
        :data:`~calib.model.parameters.COMBINATION_NAMES` order.

    Raises
    ------
    InputError
        The document has no covariance (``field="covariance"``): a check cannot test against it.
    """
    if doc.covariance is None:
        raise InputError(
            "the calibration has no covariance of its combinations: a check cannot test against it", field="covariance"
        )
    order = list(doc.covariance_order)
    if sorted(order) != sorted(COMBINATION_NAMES):
        raise InputError(f"must name {', '.join(COMBINATION_NAMES)}, got {order}", field="covariance_order")
    idx = [order.index(k) for k in COMBINATION_NAMES]
    cov = np.asarray(doc.covariance, dtype=np.float64)
    if cov.shape != (4, 4):
        raise InputError(f"must be 4x4, got shape {cov.shape}", field="covariance")
    return CombinationEstimate.from_dicts(doc.combinations, cov[np.ix_(idx, idx)])


def updated_calibration(
    in_force: CalibrationDocument,
    update: UpdateResult,
    *,
    software_version: str,
    date: str | None = None,
    dataset_hash: str | None = None,
    check: str | None = None,
) -> CalibrationDocument:
    """The ``i4cal.calibration/1`` document of an accepted update: the updated combinations and covariance, the
    seven parameters completed with the calibration in force's H, S, q03 (:data:`UPDATE_COMPLETION_RULE`), the rest
    of the provenance said (``check``: the check's id; ``source.updated_from``: the calibration in force's run,
    method and date).

    Parameters
    ----------
    in_force : CalibrationDocument
        The calibration in force, the update's base.
    update : UpdateResult
        The check's accepted update (combinations in metres, covariance in m^2).
    software_version : str
        The version recorded in the new document.
    date : str, optional
        ISO 8601 time of the update (``date`` and ``exported_at``).
    dataset_hash : str, optional
        SHA-256 of the check's dataset.
    check : str, optional
        The check's id (``source.check``).

    Returns
    -------
    CalibrationDocument
        The updated calibration (seven parameters in metres, their std in metres, None where fixed).

    Raises
    ------
    InputError
        The update was refused (``field="update"``): it must not be applied.
    """
    from calib.identify.export import Completion, Source

    if not update.accepted:
        raise InputError(f"the update was refused: {update.reason}", field="update")
    est = update.estimate
    combos = {k: float(v) for k, v in zip(COMBINATION_NAMES, est.value_m, strict=True)}
    previous = in_force.to_parameters()
    params = I4Parameters.from_combinations(combos, previous)
    std = est.std_m()
    std4: dict[str, float | None] = {k: float(v) for k, v in zip(COMBINATION_NAMES, std, strict=True)}
    seven_std: dict[str, float | None] = {
        "H": None,
        "q02": 2.0 * float(std[2]),
        "q03": None,
        "q04": 2.0 * float(std[3]),
        "S": None,
        "D": float(std[1]),
        "L": float(std[0]),
    }
    fixed = ["H", "S", "q03"]
    return in_force.model_copy(
        update={
            "run": None,
            "method": in_force.method,
            "method_choice": f"updated by a check ({', '.join(update.reestimated)} re-estimated from the check's "
            f"frames, the rest from the calibration in force)",
            "date": date,
            "exported_at": date,
            "software_version": software_version,
            "dataset_hash": dataset_hash,
            "seven": params.seven(),
            "seven_std": seven_std,
            "identified": [n for n in params.seven() if n not in fixed],
            "fixed_at_nominal": fixed,
            "completion": Completion(rule=UPDATE_COMPLETION_RULE, text=UPDATE_COMPLETION_TEXT),
            "combinations": combos,
            "combinations_std": std4,
            "covariance": est.covariance_m2.tolist(),
            "covariance_order": list(COMBINATION_NAMES),
            "validation": None,
            "warnings": [],
            "source": Source.model_validate(
                {
                    "result_sha256": None,
                    "result_file": None,
                    "check": check,
                    "updated_from": {"run": in_force.run, "method": in_force.method, "date": in_force.date},
                }
            ),
        },
        deep=True,
    )


__all__ = [
    "UPDATE_COMPLETION_RULE",
    "CombinationEstimate",
    "DriftResult",
    "DriftSettings",
    "UpdateResult",
    "check_drift",
    "in_force_estimate",
    "max_abs_z_threshold",
    "update_from_check",
    "updated_calibration",
]

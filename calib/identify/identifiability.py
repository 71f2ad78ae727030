"""Identifiability analysis: numerical rank of a method's identification Jacobian over the seven parameters.

The Jacobian of the method's measurement model (its :class:`calib.identify.pose_set_model.PoseSetModel`, read through
the
registry: :func:`calib.identify.registry.method_identifiability`) with respect to (H, q02, q03, q04, S, D, L) is
computed numerically at a parameter set and pose set; nuisance parameters of the method (camera and board
transforms) are projected out. Its singular values give the rank and the condition number; the row
space, brought to reduced row-echelon form with the column order (L, D, q02, q04, H, S, q03), gives
the identifiable combinations in a readable form. For the combined and end-effector methods on a
good pose set it finds the paper's four: L, H - D, S - q02/2, S - (q04 - q03)/2.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from calib.model.kinematics import ikm
from calib.model.parameters import PARAMETER_NAMES, I4Parameters
from calib.numerics.numdiff import central_jacobian

_ORDER = ("L", "D", "q02", "q04", "H", "S", "q03")
_KNOWN = {
    "L": {"L": 1.0},
    "H-D": {"H": 1.0, "D": -1.0},
    "S-q02/2": {"S": 1.0, "q02": -0.5},
    "S-(q04-q03)/2": {"S": 1.0, "q04": -0.5, "q03": 0.5},
}


def analyse(
    fun: Callable[[np.ndarray], np.ndarray], params: I4Parameters, n_nuisance: int = 0, rel_tol: float = 1e-7
) -> dict:
    """Rank, singular values, condition number and identifiable combinations of a measurement model.

    Parameters
    ----------
    fun : callable
        ``fun(x) -> (M,)``: the measurements predicted for ``x`` (7 + n_nuisance,), the seven parameters (m) first.
    params : I4Parameters
        The linearisation point.
    n_nuisance : int
        Nuisance unknowns after the seven (projected out).
    rel_tol : float
        Singular values below ``rel_tol`` times the largest count as zero.

    Returns
    -------
    dict
        ``rank``, ``singular_values``, ``condition_number``, ``identifiable_combinations`` (readable),
        ``paper_combinations_in_row_space``, ``finds_paper_four``, ``non_identifiable_directions``.
    """
    x0 = np.concatenate([np.asarray(params.vector()), np.zeros(n_nuisance)])
    J = central_jacobian(fun, x0, 1e-6)
    J7 = J[:, :7]
    if n_nuisance:
        Jn = J[:, 7:]
        Q, _ = np.linalg.qr(Jn)
        J7 = J7 - Q @ (Q.T @ J7)
    _, s, Vt = np.linalg.svd(J7, full_matrices=False)
    tol = s[0] * rel_tol
    rank = int(np.sum(s > tol))
    basis = Vt[:rank]
    # reduced row echelon form in a readable column order
    perm = [PARAMETER_NAMES.index(n) for n in _ORDER]
    Bp = basis[:, perm]
    rows = _rref(Bp)
    combos = []
    for row in rows:
        terms = []
        for coef, name in zip(row, _ORDER, strict=True):
            if abs(coef) > 1e-6:
                terms.append((coef, name))
        combos.append(_fmt(terms))
    found = {}
    for key, coeffs in _KNOWN.items():
        v = np.zeros(7)
        for n, c in coeffs.items():
            v[PARAMETER_NAMES.index(n)] = c
        resid = np.linalg.norm(v - basis.T @ (basis @ v)) / np.linalg.norm(v)
        found[key] = bool(resid < 1e-5)
    return {
        "rank": rank,
        "singular_values": s.tolist(),
        "condition_number": float(s[0] / s[rank - 1]),
        "identifiable_combinations": combos,
        "paper_combinations_in_row_space": found,
        "finds_paper_four": bool(rank == 4 and all(found.values())),
        "non_identifiable_directions": [
            dict(zip(PARAMETER_NAMES, np.round(v, 6).tolist(), strict=True)) for v in Vt[rank:]
        ],
    }


def _rref(M: np.ndarray, tol: float = 1e-9) -> list[np.ndarray]:
    A = M.copy()
    rows, cols = A.shape
    r = 0
    out = []
    for c in range(cols):
        if r >= rows:
            break
        piv = r + int(np.argmax(np.abs(A[r:, c])))
        if abs(A[piv, c]) < tol:
            continue
        A[[r, piv]] = A[[piv, r]]
        A[r] /= A[r, c]
        for k in range(rows):
            if k != r:
                A[k] -= A[k, c] * A[r]
        r += 1
    for k in range(r):
        out.append(A[k])
    return out


def _fmt(terms: list[tuple[float, str]]) -> str:
    s = ""
    for i, (c, n) in enumerate(terms):
        sign = "-" if c < 0 else "+"
        mag = abs(c)
        coef = "" if abs(mag - 1) < 1e-6 else f"{mag:.4g} "
        s += (("- " if sign == "-" else "") if i == 0 else f" {sign} ") + coef + n
    return s


__all__ = ["analyse", "ikm"]

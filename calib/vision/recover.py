"""Rods lost in their search bands: how many, and the lines measured so far as the input of a robust refit.

A rod is *lost in its search* when it was predicted inside the image and in view but nothing there passed as it:
too few or too scattered limb edges, a line of the wrong polarity (the gap between its leg's two rods), both rods of
a leg on the same image. These depend on where the prediction put the band; a rod out of the image, seen end-on or
hidden by the board does not. A bench within a few millimetres of nominal loses hardly any rod in its search; one so
far off nominal that the prediction falls between a leg's rods loses a large share of them, and the first refit
(:func:`calib.vision.repredict.refit_prediction` with each line its own rod) can settle on a wrong geometry. When
more than ``ExtractOptions.recover_lost_share`` are lost, :func:`calib.vision.extract.extract_dataset` refits the
prediction robustly (:func:`calib.vision.repredict.refit_prediction` with ``mixture`` and ``starts``) from the lines
returned here and measures every frame again.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calib.numerics.transforms import Rigid
from calib.vision.repredict import MeasuredRod
from calib.vision.rods import ROD_KEYS, rod_name

#: the robust refit's starting points besides the prediction's own (:func:`calib.vision.repredict.refit_prediction`)
STARTS = 16

#: the beginnings of the reasons (:mod:`calib.vision.rods.measure`) of a rod lost in its search band
LOST_IN_SEARCH = (
    "too few limb edge points",
    "limb line fit failed",
    "limb edges too scattered",
    "interpretation planes nearly parallel",
    "measured on the gap between its leg's two rods",
    "both rods of the leg matched the same rod image",
    "brighter than its surroundings",
    "darker than its surroundings",
)


def lost_in_search(observations: dict[str, Any]) -> tuple[int, int]:
    """Rods lost in their search bands, and rods looked for (found or lost in their search).

    Parameters
    ----------
    observations : dict
        An observations v1 document (:func:`calib.vision.extract.extract_dataset`'s).

    Returns
    -------
    (int, int)
    """
    lost = found = 0
    for f in observations["frames"]:
        missing = f.get("missing") or {}
        for leg, rod in ROD_KEYS:
            if f["legs"][str(leg + 1)][rod] is not None:
                found += 1
            elif missing.get(rod_name(leg, rod), "").startswith(LOST_IN_SEARCH):
                lost += 1
    return lost, found + lost


def measured_lines(observations: dict[str, Any]) -> tuple[np.ndarray, list[MeasuredRod], dict[int, Rigid]]:
    """The encoder values, measured rod axes and board poses of an observations v1 document's frames.

    Parameters
    ----------
    observations : dict
        An observations v1 document (:func:`calib.vision.extract.extract_dataset`).

    Returns
    -------
    q : ndarray, shape (N, 4)
        Metres, one row per frame.
    rods : list of MeasuredRod
        Indexed into ``q`` (camera frame, metres).
    boards : dict
        Frame index into ``q`` -> measured ``camera_from_board``.
    """
    frames = observations["frames"]
    q = np.array([f["q"] for f in frames], dtype=np.float64).reshape(-1, 4)
    rods: list[MeasuredRod] = []
    boards: dict[int, Rigid] = {}
    for k, f in enumerate(frames):
        if f.get("board") is not None:
            boards[k] = Rigid(np.asarray(f["board"]["R"], dtype=np.float64), np.asarray(f["board"]["t"]))
        for leg, rod in ROD_KEYS:
            m = f["legs"][str(leg + 1)][rod]
            if m is not None and m.get("point") is not None:
                rods.append(MeasuredRod(k, leg, rod, np.asarray(m["point"], dtype=np.float64), np.asarray(m["u"])))
    return q, rods, boards

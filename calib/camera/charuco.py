"""The ChArUco board as OpenCV builds it from its spec (:class:`calib.formats.dataset.BoardSpec`): the board object
and its nominal corners, shared by the camera's calibration and the extraction."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.formats.dataset import BoardSpec

Array = NDArray[np.float64]


def make_board(spec: BoardSpec) -> cv2.aruco.CharucoBoard:
    """The OpenCV board described by ``spec`` (legacy layout when ``spec.legacy_pattern``).

    Parameters
    ----------
    spec : BoardSpec
        Squares, square and marker lengths (metres), ArUco dictionary name and layout.

    Returns
    -------
    cv2.aruco.CharucoBoard
        The board, lengths in metres.

    Raises
    ------
    ValueError
        ``spec.dictionary`` names no ArUco dictionary of OpenCV.
    """
    name = spec.dictionary
    if not hasattr(cv2.aruco, name):
        raise ValueError(f"unknown ArUco dictionary {name!r}")
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
    board = cv2.aruco.CharucoBoard(
        (spec.squares_x, spec.squares_y), spec.square_length_m, spec.marker_length_m, dictionary
    )
    board.setLegacyPattern(bool(spec.legacy_pattern))
    return board


def board_corners(spec: BoardSpec) -> tuple[NDArray[np.int_], Array]:
    """All ChArUco corner ids (M,) and their nominal positions in the board frame (M, 3), metres.

    Parameters
    ----------
    spec : BoardSpec
        The board.

    Returns
    -------
    ids : ndarray of int, shape (M,)
        Corner ids ``0 .. M-1``.
    points : ndarray, shape (M, 3)
        Nominal corner positions in the board frame (metres, z = 0).
    """
    pts = np.asarray(make_board(spec).getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
    return np.arange(pts.shape[0]), pts

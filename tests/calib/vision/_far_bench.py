"""Shared by the far-bench tests: how many rods an extraction lost, and how many lie beyond their own bound."""

from __future__ import annotations

from typing import Any

import numpy as np

from calib.parameters import I4Parameters
from calib.vision.repredict import rod_ends_camera
from drivers.sim.twin import BenchGeometry


def lost_and_far(observations: dict[str, Any], truth: I4Parameters, g: BenchGeometry) -> tuple[int, int]:
    """Rods lost (neither found nor out of the image / behind the board) and rods found whose direction is beyond
    its own covariance's 99.9% bound (chi-square, 2 degrees of freedom) from the truth's."""
    lost = far = 0
    for f in observations["frames"]:
        q = np.asarray(f["truth"]["q"])
        top, bottom, _ = rod_ends_camera(truth, q[None], g.camera_from_base, g.rod_spacing_m)
        for i in range(4):
            for j in range(2):
                m = f["legs"][str(i + 1)][j]
                if m is None:  # lost, unless out of the image or behind the board
                    lost += int(not f["missing"].get(f"leg{i + 1}.rod{j}", "").startswith("not enough of the rod"))
                    continue
                u_true = bottom[0, i, j] - top[0, i, j]
                u_true /= np.linalg.norm(u_true)
                u = np.asarray(m["u"]) * np.sign(np.asarray(m["u"]) @ u_true)
                d = u - u_true
                cov = np.asarray(m["cov_u"]) + 1e-12 * np.eye(3)
                # the direction has two degrees of freedom: the distance in the plane normal to u_true
                P = np.eye(3) - np.outer(u_true, u_true)
                d2 = float(d @ P @ np.linalg.pinv(P @ cov @ P, rcond=1e-9) @ P @ d)
                far += int(d2 > 13.8)  # chi-square(2) 99.9%
    return lost, far

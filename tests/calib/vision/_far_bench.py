"""Shared by the far-bench tests: their plan, exact board poses, and how many rods an extraction lost or misplaced."""

from __future__ import annotations

from typing import Any

import numpy as np

from calib.formats.plan import Plan, make_plan
from calib.model.kinematics import dkm
from calib.model.parameters import NOMINAL, I4Parameters
from calib.numerics.transforms import Rigid, rot_z
from calib.vision.extract import RODS_NOT_READ
from calib.vision.repredict import rod_ends_camera
from drivers.sim.twin import BenchGeometry


def far_plan() -> Plan:
    """A 42-frame full plan (8 base, 12 fit, 3 per lock phase, 2 validation poses) without its guided line."""
    plan = make_plan("full", NOMINAL, seed=0, n_base=8, n_fit=12, n_lock=3, n_validation=2)
    return Plan(name="far", steps=[s for s in plan.steps if s.phase != "line"])


def exact_boards(g: BenchGeometry, q: np.ndarray) -> dict[int, Rigid]:
    """The true ``camera_from_board`` at each row of ``q`` (N, 4), keyed by row."""
    truth = g.truth
    return {
        k: g.camera_from_base
        @ Rigid(rot_z(p[3] / truth.T_per_rad), np.array([p[0], truth.H + p[1], p[2]]))
        @ g.ee_from_board
        for k, p in enumerate(dkm(truth, q))
    }


def lost_and_far(observations: dict[str, Any], truth: I4Parameters, g: BenchGeometry) -> tuple[int, int]:
    """Rods lost (neither found nor out of the image / behind the board) and rods found whose direction is beyond
    its own covariance's 99.9% bound (chi-square, 2 degrees of freedom) from the truth's; the frames of a phase whose
    rods are not read (:data:`calib.vision.extract.ROD_PHASES`) left out."""
    lost = far = 0
    for f in observations["frames"]:
        if f["missing"].get("rods") == RODS_NOT_READ:
            continue
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

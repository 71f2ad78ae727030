"""Geometric digital twin of the I4 bench: true geometry, camera, board, rods, and noisy observations.

The twin holds a *true* geometry that differs from the nominal one by a few millimetres (the size
of the gaps between the paper's a priori and identified values, Table I), a camera placed as in the
paper (near the plane z_B = 0 between the rails, looking down at the traveling plate), and a
ChArUco board on the end-effector. It executes a plan (joint targets computed with the nominal
model, as a real bench does) on the true mechanism and writes observations v1 with the truth
alongside.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np

from calib.formats.observations import new_document
from calib.formats.plan import Plan, line_poses, make_plan
from calib.model.kinematics import base_from_ee, dkm, ikm, joint_points
from calib.model.parameters import NOMINAL, I4Parameters
from calib.numerics.transforms import Rigid, rotvec_to_matrix, unit

#: The twin's default true geometry: nominal plus a few millimetres (metres).
DEFAULT_TRUTH = NOMINAL.replace(H=0.4040, q02=1.3775, q03=0.0030, q04=1.3870, S=0.0575, D=0.0620, L=0.9965)

# camera looking down (-z_B): x_C = x_B, y_C = -y_B, z_C = -z_B, then a small tilt
_R_BASE_FROM_CAM_NOMINAL = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def default_base_from_camera() -> Rigid:
    """Camera at actuator level between the rails, mid-range in x, looking down with a small tilt."""
    tilt = rotvec_to_matrix(np.array([0.035, -0.025, 0.06]))
    return Rigid(tilt @ _R_BASE_FROM_CAM_NOMINAL, np.array([0.95, 0.40, 0.03]))


def default_ee_from_board(board_size_m: tuple[float, float] = (0.24, 0.16)) -> Rigid:
    """Board on top of the plate facing the camera (its z axis points down, -z_E), slightly off-centre.

    The board frame is OpenCV's: origin at a corner, x along the squares_x side, z into the board.
    """
    R = rotvec_to_matrix(np.array([0.008, -0.006, 0.17])) @ _R_BASE_FROM_CAM_NOMINAL
    centre_in_board = np.array([board_size_m[0] / 2, board_size_m[1] / 2, 0.0])
    centre_in_ee = np.array([0.012, -0.007, 0.035])
    return Rigid(R, centre_in_ee - R @ centre_in_board)


@dataclass(frozen=True)
class NoiseSpec:
    """Noise of the geometric twin's observations (standard deviations)."""

    rod_direction_rad: float = 5e-4
    rod_point_m: float = 5e-4
    board_rotation_rad: float = 3e-4
    board_translation_m: tuple[float, float, float] = (1e-4, 1e-4, 3e-4)  # camera x, y, depth
    encoder_m: float = 1e-6

    @classmethod
    def zero(cls) -> NoiseSpec:
        return cls(0.0, 0.0, 0.0, (0.0, 0.0, 0.0), 0.0)

    def scaled(self, k: float) -> NoiseSpec:
        return NoiseSpec(
            self.rod_direction_rad * k,
            self.rod_point_m * k,
            self.board_rotation_rad * k,
            cast("tuple[float, float, float]", tuple(x * k for x in self.board_translation_m)),  # three in, three out
            self.encoder_m * k,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "rod_direction_rad": self.rod_direction_rad,
            "rod_point_m": self.rod_point_m,
            "board_rotation_rad": self.board_rotation_rad,
            "board_translation_m": list(self.board_translation_m),
            "encoder_m": self.encoder_m,
        }


@dataclass(frozen=True)
class BenchGeometry:
    """Everything the twin needs to know about the (true) bench.

    ``rod_spacing_m``: the two rods of each parallelogram leg are offset by -/+ half of it along
    x_B from the equivalent leg A_i B_i (rod 0 on the -x_B side, rod 1 on the +x_B side).
    """

    truth: I4Parameters = DEFAULT_TRUTH
    nominal: I4Parameters = NOMINAL
    base_from_camera: Rigid = field(default_factory=default_base_from_camera)
    ee_from_board: Rigid = field(default_factory=default_ee_from_board)
    rod_radius_m: float = 0.008
    rod_spacing_m: float = 0.06

    @property
    def camera_from_base(self) -> Rigid:
        return self.base_from_camera.inverse()

    # -- truth at a joint vector --------------------------------------------------------------
    def base_from_ee(self, pose: np.ndarray) -> Rigid:
        return Rigid(*base_from_ee(self.truth, pose))

    def camera_from_board(self, pose: np.ndarray) -> Rigid:
        return self.camera_from_base @ self.base_from_ee(pose) @ self.ee_from_board

    def rod_segments_base(self, q: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rod end points (upper at the actuator, lower at the plate) in the base frame, (4, 2, 3) each."""
        A, B = joint_points(self.truth, q[None], pose[None])
        off = np.array([-0.5, 0.5])[:, None] * self.rod_spacing_m * np.array([1.0, 0.0, 0.0])
        top = A[0][:, None, :] + off[None]
        bottom = B[0][:, None, :] + off[None]
        return top, bottom

    def rod_lines_camera(self, q: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rod axes in the camera frame: unit directions (A to B) and the axis point closest to the camera.

        Returns
        -------
        u, p : ndarray, shape (4, 2, 3)
        """
        top, bottom = self.rod_segments_base(q, pose)
        cb = self.camera_from_base
        top_c = cb.apply(top)
        bot_c = cb.apply(bottom)
        u = unit(bot_c - top_c)
        # foot of the perpendicular from the camera centre (origin) to each axis
        s = -np.einsum("ijk,ijk->ij", top_c, u)
        p = top_c + s[..., None] * u
        return u, p


# ---------------------------------------------------------------------------------------------
def _perturb_direction(u: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    if sigma == 0:
        return u
    e = rng.normal(0.0, sigma, size=u.shape)
    e -= np.sum(e * u, axis=-1, keepdims=True) * u
    return unit(u + e)


def _perturb_point(p: np.ndarray, u: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    if sigma == 0:
        return p
    e = rng.normal(0.0, sigma, size=p.shape)
    e -= np.sum(e * u, axis=-1, keepdims=True) * u
    return p + e


@dataclass
class GeometricTwin:
    """Executes plans on the true mechanism and produces noisy observations v1."""

    geometry: BenchGeometry = field(default_factory=BenchGeometry)
    noise: NoiseSpec = field(default_factory=NoiseSpec)

    def true_poses(self, plan: Plan) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """(phase, true q, true pose) for every frame of a plan."""
        g = self.geometry
        out: list[tuple[str, np.ndarray, np.ndarray]] = []
        for step in plan.steps:
            if step.line is not None:
                # the operator guides the true end-effector along a truly straight ruler
                poses = line_poses(step.line)
                for pose, q in zip(poses, ikm(g.truth, poses), strict=True):
                    out.append((step.phase, q, pose))
            elif step.phase != "camera":
                q = np.asarray(step.q, dtype=np.float64)
                out.append((step.phase, q, dkm(g.truth, q)))
        return out

    def frame(
        self, phase: str, q: np.ndarray, pose: np.ndarray, rng: np.random.Generator, with_truth: bool = True
    ) -> dict[str, Any]:
        g = self.geometry
        n = self.noise
        cb = g.camera_from_board(pose)
        R = cb.R
        t = cb.t
        if n.board_rotation_rad:
            R = rotvec_to_matrix(rng.normal(0.0, n.board_rotation_rad, 3)) @ R
        if any(n.board_translation_m):
            t = t + rng.normal(0.0, 1.0, 3) * np.asarray(n.board_translation_m)
        u, p = g.rod_lines_camera(q, pose)
        u_m = _perturb_direction(u, n.rod_direction_rad, rng)
        p_m = _perturb_point(p, u, n.rod_point_m, rng)
        q_m = q + rng.normal(0.0, n.encoder_m, 4) if n.encoder_m else q
        legs = {
            str(i + 1): [{"u": u_m[i, j].tolist(), "point": p_m[i, j].tolist()} for j in range(2)] for i in range(4)
        }
        fr: dict[str, Any] = {
            "phase": phase,
            "q": q_m.tolist(),
            "board": {"R": R.tolist(), "t": t.tolist()},
            "legs": legs,
        }
        if with_truth:
            fr["truth"] = {"q": q.tolist(), "pose": pose.tolist()}
        return fr

    def observations(self, plan: Plan | None = None, seed: int = 0) -> dict[str, Any]:
        """Simulate a plan (default: the paper's full plan) into an observations v1 dict."""
        g = self.geometry
        plan = plan or make_plan("full", g.nominal, seed=seed)
        rng = np.random.default_rng(seed)
        frames = [self.frame(ph, q, pose, rng) for ph, q, pose in self.true_poses(plan)]
        return new_document(
            g.nominal,
            frames,
            truth=self.truth_dict(),
            noise=self.noise.to_dict(),
            generator={"name": "i4cal geometric twin", "seed": seed, "plan": plan.name},
        )

    def truth_dict(self) -> dict[str, Any]:
        g = self.geometry
        return {
            "parameters": g.truth.as_dict(),
            "combinations": g.truth.combinations(),
            "camera_from_base": g.camera_from_base.to_dict(),
            "ee_from_board": g.ee_from_board.to_dict(),
            "rod_radius_m": g.rod_radius_m,
            "rod_spacing_m": g.rod_spacing_m,
        }

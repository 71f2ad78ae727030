"""Image-level twin: renders what the bench camera sees for the twin's true geometry.

Ray casting per pixel through the *true* camera (pinhole + OpenCV distortion): every output pixel's
ray is the exact undistorted direction of that pixel (``cv2.undistortPointsIter`` on the pixel grid,
computed once), so distortion is exact and no resampling of a rendered image is needed.

* Rods: finite cylinders; the silhouette of each is the wedge between its two tangent
  (interpretation) planes through the camera centre (exact perspective), anti-aliased by the signed
  pixel distance to each limb line, cut at the rod's ends, shaded by the surface normal across the
  rod (Lambert + a specular streak), composited far to near with a depth test.
* Board: the ChArUco image from ``board.generateImage`` (with a white margin) on its plane,
  textured by ray-plane intersection (mip-mapped ``cv2.remap``), with a manufacturing error: the
  true corner positions differ from the nominal ones by a smooth in-plane deformation whose RMS over
  the corners is ``board_error_m``.
* Background texture with straight "bench" edges, Gaussian optical blur, Gaussian sensor noise;
  every level can be set to zero.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.camera.charuco import make_board
from calib.formats.camera import CameraModel
from calib.formats.dataset import BoardSpec
from calib.numerics.transforms import Rigid
from calib.vision.rods import limb_planes
from drivers.sim._memory import keep_freed_memory
from drivers.sim.twin import BenchGeometry

keep_freed_memory()  # a frame's temporaries are reused, not page-faulted in again (drivers/sim/_memory.py)

_F = 3.6e-3 / 4.65e-6


@dataclass(frozen=True)
class RenderSettings:
    """Image-formation settings of the rendered camera (true intrinsics and degradation levels)."""

    width: int = 1024
    height: int = 768
    fx: float = _F
    fy: float = _F
    cx: float = 515.3
    cy: float = 380.6
    dist: tuple[float, ...] = (-0.30, 0.10, 4e-4, -3e-4, 0.0)
    noise_sigma: float = 2.0  #: sensor noise, grey levels (std)
    blur_sigma_px: float = 0.8  #: Gaussian optical blur, pixels (0: none)
    texture: float = 1.0  #: background texture amplitude (0: flat background)
    clutter_lines: int = 12  #: straight background edges (0: none)
    board_error_m: float = 2e-4  #: RMS deviation of the true board corners from the nominal ones
    board: BoardSpec = field(default_factory=BoardSpec)
    board_margin_m: float = 0.012  #: white margin around the printed pattern
    #: the camera phase's board centres lie within +/- this in normalized x (0.75 of it in y). With the whole board
    #: in view its inner corners reach ~60% of the image's corner radius at the default, ~70% at 0.75 (measured on
    #: 30-view phases): not enough to determine k3 either way (its std 0.01-0.035)
    camera_view_spread: float = 0.45
    #: every rod's silhouette widened by this much on each side (image px, wherever the rod is in the image;
    #: negative: narrowed), on top of what blur and shading do: a known limb-edge bias, to check the methods' models
    #: of it (0: the rod as it is)
    rod_edge_offset_px: float = 0.0
    #: the rods' shading (a broad diffuse light, an asymmetric term and a specular streak); False: every rod one
    #: uniform grey, to tell what the shading does to the limb edges from what the blur and the edge model do
    rod_shading: bool = True

    def camera(self) -> CameraModel:
        K = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        return CameraModel(K, np.asarray(self.dist, dtype=np.float64), self.width, self.height)

    @classmethod
    def clean(cls, **kw) -> RenderSettings:
        """No noise, no blur, no texture, no clutter, an exact board."""
        base: dict[str, Any] = dict(noise_sigma=0.0, blur_sigma_px=0.0, texture=0.0, clutter_lines=0, board_error_m=0.0)
        base.update(kw)
        return cls(**base)


@functools.lru_cache(maxsize=4)
def _ray_grid(K: tuple, dist: tuple, width: int, height: int) -> np.ndarray:
    cam = CameraModel(np.asarray(K).reshape(3, 3), np.asarray(dist), width, height)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    xn = cam.undistort_points(np.column_stack([u.ravel(), v.ravel()]))
    return xn.reshape(height, width, 2).astype(np.float32)


class BenchRenderer:
    """Renders the bench (four parallelogram legs, the board on the end-effector) as the camera sees it.

    Parameters
    ----------
    geometry : BenchGeometry
        The true bench (twin).
    settings : RenderSettings
    seed : int
        Seeds the background, the board's manufacturing error and the per-image noise.
    """

    def __init__(
        self, geometry: BenchGeometry | None = None, settings: RenderSettings | None = None, seed: int = 0
    ) -> None:
        self.geometry = geometry or BenchGeometry()
        self.settings = settings or RenderSettings()
        s = self.settings
        self.camera = s.camera()
        self.rng = np.random.default_rng(seed)
        self.rays = _ray_grid(tuple(self.camera.K.ravel()), tuple(self.camera.dist), s.width, s.height)
        self.background = self._make_background(np.random.default_rng([seed, 1]))
        self._make_board(np.random.default_rng([seed, 2]))

    # -- scene pieces -----------------------------------------------------------------------------
    def _make_background(self, rng: np.random.Generator) -> np.ndarray:
        s = self.settings
        h, w = s.height, s.width
        bg = np.full((h, w), 50.0, dtype=np.float32)
        if s.texture > 0:
            for scale, amp in ((64, 14.0), (16, 7.0), (4, 3.0)):
                small = rng.normal(0.0, 1.0, (h // scale + 2, w // scale + 2)).astype(np.float32)
                big = cv2.resize(small, (w + 2 * scale, h + 2 * scale), interpolation=cv2.INTER_CUBIC)
                bg += s.texture * amp * big[scale : scale + h, scale : scale + w]
        if s.clutter_lines > 0:
            layer = np.zeros((h * 4, w * 4), dtype=np.float32)
            for _ in range(s.clutter_lines):
                p0 = rng.uniform([0, 0], [w, h])
                ang = rng.uniform(0, np.pi)
                d = np.array([np.cos(ang), np.sin(ang)]) * rng.uniform(80, 600)
                val = float(rng.choice([-1, 1]) * rng.uniform(20, 45))
                th = int(rng.integers(2, 7))
                cv2.line(
                    layer,
                    tuple(int(x) for x in (p0 * 4)),
                    tuple(int(x) for x in ((p0 + d) * 4)),
                    val,
                    thickness=th * 4,
                    lineType=cv2.LINE_AA,
                )
            bg += cv2.resize(layer, (w, h), interpolation=cv2.INTER_AREA)
        return np.clip(bg, 5, 250)

    def _make_board(self, rng: np.random.Generator) -> None:
        s = self.settings
        spec = s.board
        self.board_spec = spec
        board = make_board(spec)
        ppm = 3000.0  # texels per metre of the finest level
        wpx = round(spec.squares_x * spec.square_length_m * ppm)
        hpx = round(spec.squares_y * spec.square_length_m * ppm)
        pattern = board.generateImage((wpx, hpx), marginSize=0, borderBits=1).astype(np.float32)
        mpx = round(s.board_margin_m * ppm)
        tex = np.full((hpx + 2 * mpx, wpx + 2 * mpx), 255.0, dtype=np.float32)
        tex[mpx : mpx + hpx, mpx : mpx + wpx] = pattern
        tex = 22.0 + tex * (215.0 / 255.0)
        self._tex_levels = [tex]
        for _ in range(4):
            # float32 in, float32 out (OpenCV's stubs type the result as any Mat)
            self._tex_levels.append(cast("NDArray[np.float32]", cv2.pyrDown(self._tex_levels[-1])))
        self._ppm = ppm
        self._margin_m = s.board_margin_m
        # manufacturing error: delta(p) = quadratic polynomial field (2 components) scaled to the set RMS
        W, H = spec.size_m
        self._err_coef = np.zeros((2, 6))
        ids_pts = np.asarray(board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        self.board_points_nominal = ids_pts
        if s.board_error_m > 0:
            coef = rng.normal(0.0, 1.0, (2, 6))
            coef[:, 0] = 0.0  # no pure translation: it would only move the board frame
            self._err_coef = coef
            d = self._delta(ids_pts[:, 0], ids_pts[:, 1])
            rms = float(np.sqrt(np.mean(np.sum(d**2, axis=0))))
            self._err_coef = coef * (s.board_error_m / rms)
        self._W, self._H = W, H
        p = ids_pts[:, :2].copy()
        for _ in range(3):  # p_true - delta(p_true) = p_nominal
            p = ids_pts[:, :2] + self._delta(p[:, 0], p[:, 1]).T
        self.board_points_true = np.column_stack([p, np.zeros(len(p))])

    def _delta(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """In-plane deviation (2, N) of the true board at true board coordinates x, y (metres)."""
        W, H = self.settings.board.size_m
        a = (x - W / 2) / W
        b = (y - H / 2) / H
        basis = np.stack([np.ones_like(a), a, b, a * a, a * b, b * b])
        return self._err_coef @ basis.reshape(6, -1)

    # -- rendering ----------------------------------------------------------------------------------
    def _bbox(self, pts_cam: np.ndarray, pad: float) -> tuple[int, int, int, int] | None:
        pts = pts_cam[pts_cam[:, 2] > 1e-3]
        if len(pts) == 0:
            return None
        px = self.camera.project(pts)
        s = self.settings
        x0 = int(max(np.floor(px[:, 0].min() - pad), 0))
        x1 = int(min(np.ceil(px[:, 0].max() + pad), s.width))
        y0 = int(max(np.floor(px[:, 1].min() - pad), 0))
        y1 = int(min(np.ceil(px[:, 1].max() + pad), s.height))
        if x1 <= x0 or y1 <= y0:
            return None
        return x0, y0, x1, y1

    def _normal_scale(self, mx: np.ndarray, my: np.ndarray, line: np.ndarray) -> np.ndarray:
        """Image pixels per ideal pixel across the image line of ``line`` (normalized coordinates ``l . (x, y, 1) =
        0``) at the points (mx, my): the distortion's local area scale over its stretch along the line."""
        f = self.camera.focal_px
        e = 1e-6
        x = np.stack([mx, my], axis=1)
        cam = self.camera
        ex, ey = np.array([e, 0.0]), np.array([0.0, e])
        jx = (cam.distort_normalized(x + ex) - cam.distort_normalized(x - ex)) / (2 * e * f)
        jy = (cam.distort_normalized(x + ey) - cam.distort_normalized(x - ey)) / (2 * e * f)
        t = np.array([-line[1], line[0]]) / np.hypot(line[0], line[1])
        det = np.abs(jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0])
        return det / np.hypot(jx[:, 0] * t[0] + jy[:, 0] * t[1], jx[:, 1] * t[0] + jy[:, 1] * t[1])

    def _draw_rod(self, img: np.ndarray, zbuf: np.ndarray, top: np.ndarray, bottom: np.ndarray) -> None:
        r = self.geometry.rod_radius_m
        f = self.camera.focal_px
        near = 0.02
        a, b = top.copy(), bottom.copy()
        if a[2] < near and b[2] < near:
            return
        if a[2] < near:
            a = a + (b - a) * (near - a[2]) / (b[2] - a[2])
        if b[2] < near:
            b = b + (a - b) * (near - b[2]) / (a[2] - b[2])
        seg = np.linspace(0, 1, 48)[:, None] * (b - a)[None] + a[None]
        rad_px = f * r / min(a[2], b[2])
        box = self._bbox(seg, rad_px + 4)
        if box is None:
            return
        x0, y0, x1, y1 = box
        L = float(np.linalg.norm(bottom - top))
        u = (bottom - top) / L
        hp, hm = limb_planes(top, u, r)
        ray = self.rays[y0:y1, x0:x1]
        mx, my = ray[..., 0].astype(np.float64), ray[..., 1].astype(np.float64)
        da = (hp[0] * mx + hp[1] * my + hp[2]) / np.hypot(hp[0], hp[1]) * f
        db = (hm[0] * mx + hm[1] * my + hm[2]) / np.hypot(hm[0], hm[1]) * f
        off = self.settings.rod_edge_offset_px
        # only the pixels inside the rod's wedge (a thin band of its box) can change: the rest is computed on them
        inside = np.nonzero(0.5 + 3.0 * abs(off) + np.minimum(da, db) > 0)
        if inside[0].size == 0:
            return
        mx, my, da, db = mx[inside], my[inside], da[inside], db[inside]
        if off:  # the offset is in image pixels: in the ideal ones (da, db) it is off over the lens' local scale
            ma, mb = (self._normal_scale(mx, my, h) for h in (hp, hm))
            cover = np.clip(0.5 + np.minimum(da + off / ma, db + off / mb), 0.0, 1.0)
        else:
            cover = np.clip(0.5 + np.minimum(da, db), 0.0, 1.0)
        keep = cover > 0
        mx, my, da, db, cover = mx[keep], my[keep], da[keep], db[keep], cover[keep]
        inside = (inside[0][keep], inside[1][keep])
        nrm = np.sqrt(mx * mx + my * my + 1.0)
        beta = (u[0] * mx + u[1] * my + u[2]) / nrm
        mP = (top[0] * mx + top[1] * my + top[2]) / nrm
        sb = np.maximum(1.0 - beta * beta, 1e-9)
        s_ax = (beta * mP - u @ top) / sb
        depth = mP + s_ax * beta
        depth = np.maximum(depth, 1e-3)
        scale = f * np.sqrt(sb) / depth
        cover *= np.clip(0.5 + np.minimum(s_ax, L - s_ax) * scale, 0.0, 1.0)
        tot = np.maximum(da + db, 1e-9)
        rho = np.clip((db - da) / tot, -1.0, 1.0)
        c = np.sqrt(np.maximum(1.0 - rho * rho, 0.0))  # cosine of the view angle on the surface
        # diffuse light from a broad source plus a specular streak; smooth up to the limbs
        # (matte paint: the shading flattens towards the limbs, where the surface turns away)
        shade = 140.0 + 55.0 * c**4 + 20.0 * rho * c * c + 35.0 * np.exp(-(((rho - 0.35) / 0.15) ** 2))
        if not self.settings.rod_shading:
            shade = np.full_like(shade, 170.0)
        zb = zbuf[y0:y1, x0:x1]
        sub = img[y0:y1, x0:x1]
        zin, sin = zb[inside], sub[inside]
        front = (depth < zin) & (cover > 0)
        sub[inside] = np.where(front, cover * shade + (1.0 - cover) * sin, sin)
        zb[inside] = np.where(front & (cover > 0.5), depth, zin)

    def _draw_board(self, img: np.ndarray, zbuf: np.ndarray, camera_from_board: Rigid) -> None:
        R, t = camera_from_board.R, camera_from_board.t
        W, H = self.settings.board.size_m
        m = self._margin_m
        outline = np.array([[-m, -m, 0], [W + m, -m, 0], [W + m, H + m, 0], [-m, H + m, 0]], dtype=np.float64)
        edge = np.concatenate([np.linspace(outline[i], outline[(i + 1) % 4], 12) for i in range(4)])
        oc = camera_from_board.apply(edge)
        if np.any(oc[:, 2] <= 1e-3):
            return
        box = self._bbox(oc, 3)
        if box is None:
            return
        x0, y0, x1, y1 = box
        ray = self.rays[y0:y1, x0:x1]
        mx, my = ray[..., 0].astype(np.float64), ray[..., 1].astype(np.float64)
        n = R[:, 2]
        den = n[0] * mx + n[1] * my + n[2]
        lam = (n @ t) / np.where(np.abs(den) < 1e-12, 1e-12, den)
        valid = lam > 0
        Xc = np.stack([lam * mx - t[0], lam * my - t[1], lam - t[2]], axis=-1)
        bx = Xc @ R[:, 0]
        by = Xc @ R[:, 1]
        f = self.camera.focal_px
        depth = lam * np.sqrt(mx * mx + my * my + 1.0)
        ins = np.minimum.reduce([bx + m, W + m - bx, by + m, H + m - by])
        cover = np.clip(0.5 + ins * f / np.maximum(lam, 1e-3), 0.0, 1.0) * valid
        d = self._delta(bx.ravel(), by.ravel())
        nx = (bx.ravel() - d[0]).reshape(bx.shape)
        ny = (by.ravel() - d[1]).reshape(by.shape)
        # mip level: about one texel per pixel
        texel_per_px = self._ppm * float(np.median(lam[valid])) / f if np.any(valid) else 1.0
        level = int(np.clip(np.floor(np.log2(max(texel_per_px, 1.0))), 0, len(self._tex_levels) - 1))
        tex = self._tex_levels[level]
        # level-0 texel-centre coordinates, then level L (pyrDown: texel j of level L sits at 2^L j)
        mapx = (((nx + m) * self._ppm - 0.5) / 2**level).astype(np.float32)
        mapy = (((ny + m) * self._ppm - 0.5) / 2**level).astype(np.float32)
        val = cv2.remap(tex, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=237.0)
        zb = zbuf[y0:y1, x0:x1]
        front = (depth < zb) & (cover > 0)
        sub = img[y0:y1, x0:x1]
        sub[front] = (cover * val + (1.0 - cover) * sub)[front]
        zb[front & (cover > 0.5)] = depth[front & (cover > 0.5)]

    def _finish(self, img: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        s = self.settings
        if s.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), s.blur_sigma_px)
        if s.noise_sigma > 0:
            g = rng if rng is not None else self.rng
            img = img + g.normal(0.0, s.noise_sigma, img.shape).astype(np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def render(
        self,
        q_true: np.ndarray,
        pose_true: np.ndarray,
        rng: np.random.Generator | None = None,
        board_visible: bool = True,
    ) -> np.ndarray:
        """The 8-bit mono image (height, width) for true joint values and the true pose."""
        g = self.geometry
        img = self.background.copy()
        zbuf = np.full(img.shape, np.inf, dtype=np.float64)
        top, bottom = g.rod_segments_base(np.asarray(q_true, dtype=np.float64), np.asarray(pose_true, dtype=np.float64))
        cb = g.camera_from_base
        tc, bc = cb.apply(top), cb.apply(bottom)
        order = sorted(
            ((leg, rod) for leg in range(4) for rod in range(2)),
            key=lambda k: -float(np.linalg.norm(0.5 * (tc[k] + bc[k]))),
        )
        for k in order:
            self._draw_rod(img, zbuf, tc[k], bc[k])
        if board_visible:
            self._draw_board(img, zbuf, g.camera_from_board(np.asarray(pose_true, dtype=np.float64)))
        return self._finish(img, rng)

    def render_board_view(self, camera_from_board: Rigid, rng: np.random.Generator | None = None) -> np.ndarray:
        """An image of the board alone (for the ``camera`` phase), board posed by ``camera_from_board``."""
        img = self.background.copy()
        zbuf = np.full(img.shape, np.inf, dtype=np.float64)
        self._draw_board(img, zbuf, camera_from_board)
        return self._finish(img, rng)

    def random_board_views(
        self, n: int, rng: np.random.Generator, full: bool = True, margin_px: float = 25.0
    ) -> list[Rigid]:
        """``n`` board poses for intrinsic calibration: tilted up to ~40 deg, spread over the image
        (``RenderSettings.camera_view_spread``), every corner in view (``full``), drawn by rejection sampling."""
        from calib.numerics.transforms import rotvec_to_matrix

        W, H = self.settings.board.size_m
        m = self._margin_m
        out: list[Rigid] = []
        outline = np.array([[-m, -m, 0], [W + m, -m, 0], [W + m, H + m, 0], [-m, H + m, 0]], dtype=np.float64)
        cam = self.camera
        for _ in range(5000):
            if len(out) >= n:
                break
            z = rng.uniform(0.28, 0.6)
            rv = rng.normal(0.0, 0.35, 3) * np.array([1.0, 1.0, 0.6])
            R = rotvec_to_matrix(rv)
            sp = self.settings.camera_view_spread
            xn = rng.uniform(-sp, sp, 2) * np.array([1.0, 0.75])
            centre = np.array([xn[0] * z, xn[1] * z, z])
            t = centre - R @ np.array([W / 2, H / 2, 0.0])
            pose = Rigid(R, t)
            pc = pose.apply(outline)
            if np.any(pc[:, 2] < 0.1):
                continue
            # face towards the camera: board z (into the board) away from the camera
            if R[:, 2] @ centre <= 0.3 * np.linalg.norm(centre):
                continue
            px = cam.project(pc)
            if full and (
                np.any(px < margin_px)
                or np.any(px[:, 0] > cam.width - margin_px)
                or np.any(px[:, 1] > cam.height - margin_px)
            ):
                continue
            out.append(pose)
        return out

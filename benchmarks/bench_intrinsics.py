"""What the intrinsic calibration costs, per stage and per lens-model candidate (a benchmark, not a timed test).

Run:  python benchmarks/bench_intrinsics.py DATASET [--repeat 5]

* CPU per ``calibrate_intrinsics(lens_model="auto")`` call on the dataset's camera-phase views, and per stage.
* Per candidate lens model: ``cv2.calibrateCameraROExtended`` from OpenCV's own start (the rational models' path)
  against the same fit seeded by the ``k1k2k3`` fit (the outlier test's, a shared start). OpenCV takes an initial
  guess with the released board only without its Schur-complement solver (``CALIB_DISABLE_SCHUR_COMPLEMENT``; with
  it, the guess fails an assertion), which is the first seeded column (``fit_lens_model(..., start=)``, steps solved
  by LU: what the calibration does for the models without k4-k6); the second is the seeded fit by
  ``scipy.optimize.least_squares`` (``lm``) on :class:`calib.camera.bundle.Bundle`. RSS in px^2 (they should
  agree).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
from scipy.optimize import least_squares

import calib.camera.intrinsics as cc
from calib.camera.bundle import Bundle
from calib.formats.dataset import Dataset
from calib.vision.board import BoardDetector


def camera_views(path: str) -> tuple[dict[int, tuple[Any, Any, None]], tuple[int, int], Any, Any]:
    """The dataset's camera-phase board detections as :func:`calib.camera.intrinsics.calibrate_intrinsics` takes
    them."""
    ds = Dataset.open(path)
    det = BoardDetector(ds.document.board)
    views: dict[int, tuple[Any, Any, None]] = {}
    for i, f in enumerate(ds.frames):
        if f.phase == "camera":
            d = det.detect(ds.load_image(i))
            views[i] = (np.asarray(d.ids, dtype=int), np.asarray(d.pixels).reshape(-1, 2), None)
    return views, (ds.document.camera.width, ds.document.camera.height), det.ids_all, det.points_nominal


def seeded_scipy_fit(board: cc.BoardViews, start: cc.LensFit, model: str) -> tuple[float, float]:
    """CPU s and RSS (px^2) of ``model`` fitted from ``start`` by ``least_squares(method="lm")`` on the bundle."""
    b = Bundle.of(
        start.K,
        cc.start_distortion(start, model),
        start.board_points,
        [board.image_points[k] for k in start.keys],
        list(start.rvecs),
        list(start.tvecs),
        board.fixed_point,
        cc.lens_model_params(model),
    )
    t0 = time.process_time()
    sol = least_squares(
        lambda x: np.concatenate(b.with_vector(x).residuals()),
        b.vector(),
        jac=lambda x: np.vstack(b.with_vector(x).jacobian()[1]),
        method="lm",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    return time.process_time() - t0, float(sol.fun @ sol.fun)


def seeded_fit(board: cc.BoardViews, start: cc.LensFit, model: str) -> tuple[float, float]:
    """CPU s and RSS (px^2) of ``model`` fitted by OpenCV from ``start`` (``fit_lens_model``'s ``start``: without its
    Schur solver, LU steps)."""
    t0 = time.process_time()
    fit = cc.fit_lens_model(board, model, start=start)
    return time.process_time() - t0, fit.rms_px**2 * board.n_residuals() / 2


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args(argv)
    views, size, ids, pts = camera_views(a.dataset)
    cc.calibrate_intrinsics(views, size, ids, pts, lens_model="auto")  # warm-up
    t0 = time.process_time()
    for _ in range(a.repeat):
        res = cc.calibrate_intrinsics(views, size, ids, pts, lens_model="auto")
    print(
        f"calibrate_intrinsics(auto): {1e3 * (time.process_time() - t0) / a.repeat:.0f} ms CPU per call, "
        f"{len(res.per_view_rms_px)} views, chosen {res.lens_model['chosen']}"
    )
    board = cc.select_board_views(views, ids, pts, size)
    board, first = cc.reject_outlier_views(board, "k1k2k3", cc.IntrinsicsSettings())
    print("model            from scratch ms  RSS px^2   | seeded: OpenCV ms  RSS px^2   | scipy ms  RSS px^2")
    for model in cc.LENS_MODELS:
        t0 = time.process_time()
        fit = cc.fit_lens_model(board, model)
        t_own = time.process_time() - t0
        rss_own = fit.rms_px**2 * board.n_residuals() / 2
        t_seed, rss_seed = seeded_fit(board, first, model)
        t_sp, rss_sp = seeded_scipy_fit(board, first, model)
        print(
            f"{model:16s} {1e3 * t_own:15.0f}  {rss_own:9.5f}  | {1e3 * t_seed:16.0f}  {rss_seed:9.5f}  "
            f"| {1e3 * t_sp:8.0f}  {rss_sp:9.5f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""From a bench to a calibration with nothing but the commands a real-bench user types, on the simulated bench:
`i4cal sim-bench` (background), `i4cal camera calibrate`, a bench file naming the camera file, `i4cal acquire --plan
full`, `i4cal calibrate DS --method all --json`. Every method converges; the combined method's errors against the
simulator's truth (`sim-bench --truth-out`) lie within 3 reported std; the camera file's focal length within 3 of its
std of the simulated lens's."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from calib.model.parameters import I4Parameters
from tests.drivers.test_processes import _free_base

I4CAL = [sys.executable, "-m", "i4cal"]


def _i4cal(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    out = subprocess.run([*I4CAL, *args], capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, f"i4cal {' '.join(args)}: {out.returncode}\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    return out


def _bench_file(path: Path, port: int, extra_camera: str = "") -> Path:
    path.write_text(
        f"""name = "simulated I4 bench"
[actuators]
uri = "modbus+tcp://127.0.0.1:{port}"
speed_m_s = 10.0
accel_m_s2 = 1000.0
timeout_s = 0.5
poll_s = 0.001
home_timeout_s = 10.0
[actuators.limits]
q_min = [-0.10, -0.10, -0.10, -0.10]
q_max = [0.80, 0.80, 0.80, 0.80]
[camera]
uri = "sim://127.0.0.1:{port + 2}"
timeout_s = 10.0
{extra_camera}
[operator]
uri = "sim://127.0.0.1:{port + 2}"
[acquisition]
line_rate_hz = 50.0
""",
        encoding="utf-8",
    )
    return path


@pytest.fixture(scope="module")
def sim_bench(tmp_path_factory):
    """`i4cal sim-bench --truth-out FILE` in the background: its port and the truth file."""
    port = _free_base()
    truth = tmp_path_factory.mktemp("truth") / "truth.json"
    proc = subprocess.Popen(
        [*I4CAL, "sim-bench", "--port", str(port), "--truth-out", str(truth)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        seen = [proc.stdout.readline() for _ in range(4)]
        assert any(line.startswith("actuators = ") for line in seen), seen
        yield port, truth
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_camera_calibrate_then_acquire_full_then_calibrate_all(sim_bench, tmp_path):
    from drivers.sim.render import RenderSettings

    port, truth_file = sim_bench
    t0 = time.monotonic()
    # 1. the camera's intrinsics, the simulated operator holding the board where asked
    bench = _bench_file(tmp_path / "bench.toml", port)
    out = _i4cal("camera", "calibrate", "--bench", str(bench), "-o", str(tmp_path / "camera.json"))
    assert "still missing" in out.stderr and "kept" in out.stderr  # said live, view by view
    cam = json.loads((tmp_path / "camera.json").read_text())
    assert cam["format"] == "i4cal.camera/1"
    cal = cam["calibration"]
    assert cal["lens_model"]["requested"] == "auto" and cal["lens_model"]["candidates"]
    assert cam["acquired"]["coverage"]["missing"] == [] and cam["acquired"]["coverage"]["kept"] >= 15
    true_f = RenderSettings().fx  # the simulated lens
    for name, k in (("fx", (0, 0)), ("fy", (1, 1))):
        assert abs(cam["K"][k[0]][k[1]] - true_f) < 3 * cal["std"][name], (name, cam["K"], cal["std"])
    t_camera = time.monotonic() - t0

    # 2. the bench file names it (relative to the bench file); acquire records it in the dataset
    _bench_file(tmp_path / "bench.toml", port, extra_camera='intrinsics = "camera.json"')
    ds = tmp_path / "ds"
    _i4cal("acquire", "--bench", str(bench), "--plan", "full", "--out", str(ds), "--no-progress")
    doc = json.loads((ds / "dataset.json").read_text())
    assert doc["camera"]["K"] == cam["K"] and doc["camera"]["dist"] == cam["dist"]
    import hashlib

    assert doc["camera"]["intrinsics"]["sha256"] == hashlib.sha256((tmp_path / "camera.json").read_bytes()).hexdigest()
    assert not any(f["phase"] == "camera" for f in doc["frames"])  # no camera phase: the file is the intrinsics
    t_acquire = time.monotonic() - t0 - t_camera

    # 3. calibrate the dataset with no option
    res = json.loads(_i4cal("calibrate", str(ds), "--method", "all", "--json").stdout)
    t_total = time.monotonic() - t0
    truth = I4Parameters.from_mapping(json.loads(truth_file.read_text()))
    assert set(json.loads(truth_file.read_text())) == {"H", "q02", "q03", "q04", "S", "D", "L"}
    for method, entry in res["methods"].items():
        assert entry["converged"], (method, entry.get("error"), entry.get("message"))
    comb = res["methods"]["combined"]
    err_std = {k: (comb["combinations"][k] - v) / comb["combinations_std"][k] for k, v in truth.combinations().items()}
    assert all(np.isfinite(list(err_std.values()))) and max(abs(v) for v in err_std.values()) < 3.0, err_std
    print(f"camera {t_camera:.1f} s, acquire {t_acquire:.1f} s, total {t_total:.1f} s; errors/std {err_std}")


def test_camera_calibrate_with_a_person_at_the_console(sim_bench, tmp_path):
    """`operator = "console"`: the placement said in words, Enter grabs (nobody holds a board up: the simulated camera
    shows the mechanism, its board wherever the last run left it; the grab's verdict is said either way), what is
    still missing said, q stops: exit status 2, nothing written."""
    port, _truth = sim_bench
    bench = _bench_file(tmp_path / "bench.toml", port)
    bench.write_text(bench.read_text().replace(f'uri = "sim://127.0.0.1:{port + 2}"\n[acq', 'uri = "console"\n[acq'))
    assert 'uri = "console"' in bench.read_text()
    out = subprocess.run(
        [*I4CAL, "camera", "calibrate", "--bench", str(bench), "-o", str(tmp_path / "camera.json")],
        input="\nq\n",
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 2, out.stderr
    assert "view 1: hold the board so that it spans about 45% of the image width" in out.stderr
    assert out.stdout.count("Press Enter to grab") == 2
    assert "grab 1: " in out.stderr and "still missing: the image's top-left corner" in out.stderr
    assert "stopped by the operator" in out.stderr and not (tmp_path / "camera.json").exists()

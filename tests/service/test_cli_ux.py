"""What a first-time user meets in the terminal: long steps that say what they do (on a terminal or not), tables that
fit 80 columns, a verdict (which result to load, why, the next command), argument edge cases answered clearly, the
demo leaving nothing behind unless asked, ``report DATASET`` reusing the observations already extracted, ``serve``
saying where the dashboard and the data are."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from rich.console import Console

from service.cli import main

ROOT = Path(__file__).resolve().parents[2]
BENCH_SIM = ROOT / "deploy" / "bench-sim.toml"


def cli(*args: str, env: dict[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """``i4cal ARGS`` in a child process, stdout and stderr pipes (not a terminal), as a script or CI runs it."""
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})},
    )


@pytest.fixture(scope="module")
def result_doc(tmp_path_factory) -> tuple[Path, dict]:
    """Observations of the geometric twin and their calibration with the three methods (result file, document)."""
    d = tmp_path_factory.mktemp("ux")
    obs = d / "obs.json"
    assert main(["simulate", "--out", str(obs), "--seed", "3"]) == 0
    res = d / "result.json"
    assert main(["calibrate", str(obs), "-o", str(res), "--json"]) == 0
    return obs, json.loads(res.read_text())


# -- terminal width, the verdict ------------------------------------------------------------------------------------


def test_the_tables_fit_80_columns_without_cutting_a_name(result_doc):
    from service.cli._output import print_result

    con = Console(width=80, record=True, force_terminal=False, color_system=None)
    print_result(result_doc[1], con)
    text = con.export_text()
    widths = [len(line.rstrip()) for line in text.splitlines()]
    assert max(widths) <= 80, text
    assert "…" not in text and "..." not in text, text
    for name in ("a priori", "combined", "end-effector", "legs", "S-(q04-q03)/2", "true geometry"):
        assert name in text, (name, text)
    # one uncertainty convention, said in the tables' titles
    assert "± 1 std" in text


def test_the_camera_scale_line_says_what_it_is(result_doc):
    from service.cli._output import print_result

    con = Console(width=80, record=True, force_terminal=False, color_system=None)
    print_result(result_doc[1], con)
    text = " ".join(con.export_text().split())
    assert "camera length scale vs encoders" in text and "Table II's gaps are divided by it" in text, text


def test_calibrate_says_which_result_to_load_and_what_it_wrote(result_doc, tmp_path, capsys):
    from calib.identify.verdict import verdict

    obs = result_doc[0]
    out = tmp_path / "r.json"
    assert main(["calibrate", str(obs), "-o", str(out)]) == 0
    stdout, stderr = capsys.readouterr()
    assert f"wrote {out}" in stderr
    v = verdict(json.loads(out.read_text()), str(out))
    flat = " ".join(stdout.split())
    assert f"verdict: load {v.method}:" in flat and "± 1 std" in flat
    assert f"next: i4cal export {out} -o calibration.json --method {v.method}" in flat


# -- long steps ------------------------------------------------------------------------------------------------------


def test_plan_design_not_on_a_terminal_says_what_it_is_doing(tmp_path):
    r = cli(
        "plan", "design", "--bench", str(BENCH_SIM), "--n-fit", "4", "--no-line", "--candidates", "60",
        env={"I4CAL_PROGRESS_EVERY_S": "0.2"},
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert lines[0] == "designing the plan ...", r.stderr
    assert any(line.startswith("designing the plan done") and line.endswith(" s)") for line in lines), r.stderr


def test_simulate_images_shows_its_progress(tmp_path):
    r = cli(
        "simulate", "--images", "--plan", "rotation-sweep", "--camera-views", "0", "--out", str(tmp_path / "ds"),
        env={"I4CAL_PROGRESS_EVERY_S": "0.2"},
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    done = [line for line in r.stderr.splitlines() if line.startswith("rendering frames done")]
    assert done and " 10/10" in done[0], r.stderr


# -- argument edge cases ---------------------------------------------------------------------------------------------


def test_a_negative_target_std_is_read_as_a_value_and_refused(capsys):
    assert main(["plan", "design", "--bench", str(BENCH_SIM), "--target-std", "-0.05mm"]) == 2
    err = capsys.readouterr().err
    assert "--target-std" in err and "-0.05mm" in err and "expected one argument" not in err, err


def test_an_unknown_plan_name_lists_the_plan_names(capsys):
    from calib.formats.plan import PLAN_NAMES

    assert main(["plan", "predict", "fulll", "--bench", str(BENCH_SIM)]) == 2
    err = capsys.readouterr().err
    assert "did you mean full?" in err and all(n in err for n in PLAN_NAMES), err


def test_a_design_that_leaves_a_method_unpredicted_warns_and_exits_1(tmp_path):
    plan = tmp_path / "p.json"
    r = cli("plan", "design", "--bench", str(BENCH_SIM), "--n-fit", "2", "--candidates", "60", "-o", str(plan))
    assert r.returncode == 1, r.stderr
    assert "warning: end-effector: not predicted" in r.stderr and "--n-fit 2 is too few" in r.stderr, r.stderr
    assert plan.is_file()


def test_serve_says_where_the_dashboard_and_the_data_are(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    data = tmp_path / "data"
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--data-dir", str(data)],
        stdout=subprocess.PIPE,
        stderr=(tmp_path / "serve.err").open("w"),
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    first: list[str] = []
    # read in a thread: the three lines come in one write, and a select on the pipe after the first readline would
    # not see the two the text layer has already buffered
    reader = threading.Thread(target=lambda: first.extend(proc.stdout.readline() for _ in range(3)), daemon=True)
    try:
        reader.start()
        reader.join(60)  # a serve that says nothing must not hang the test
    finally:
        proc.terminate()
        proc.wait(20)
    assert len(first) == 3, (first, (tmp_path / "serve.err").read_text()[-2000:])
    err = (tmp_path / "serve.err").read_text()[-2000:]
    assert first[0].strip() == f"i4cal dashboard: http://127.0.0.1:{port}/dashboard", (first, err)
    assert first[2].strip() == f"data directory: {data.resolve()}", first


def test_the_simulated_service_keeps_its_data_outside_the_checkout(tmp_path, monkeypatch):
    from service.settings import load_settings

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    monkeypatch.delenv("I4CAL_DATA_DIR", raising=False)
    s = load_settings(ROOT / "deploy" / "service-sim.toml")
    assert s.data_dir == tmp_path / "xdg" / "i4cal"
    assert not s.data_dir.resolve().is_relative_to(ROOT)


# -- the demo, report DATASET ----------------------------------------------------------------------------------------


def test_the_demo_leaves_nothing_behind_unless_asked(tmp_path):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    r = cli("demo", "--small", env={"TMPDIR": str(tmp)}, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert list(tmp.iterdir()) == [], list(tmp.iterdir())
    assert "nothing kept" in r.stdout and "verdict:" in r.stdout


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo") / "kept"
    r = cli("demo", "--small", "--out", str(out), timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert f"kept in {out}" in r.stdout
    return out


def test_the_demo_keeps_its_result_when_asked_and_names_it_in_the_next_command(demo_dir):
    from calib.identify.verdict import verdict

    doc = json.loads((demo_dir / "result.json").read_text())
    v = verdict(doc, str(demo_dir / "result.json"))
    assert (demo_dir / "dataset" / "dataset.json").is_file() and (demo_dir / "observations.json").is_file()
    assert v.next_command is None or str(demo_dir / "result.json") in v.next_command


def test_report_of_a_dataset_reuses_its_observations(demo_dir, tmp_path, capsys, monkeypatch):
    import calib.vision.extract as extract

    def no_extraction(*a, **k):  # a spy: the images must not be extracted again
        raise AssertionError("extracted again")

    monkeypatch.setattr(extract, "extract_dataset", no_extraction)
    out = tmp_path / "r.html"
    assert main(["report", str(demo_dir / "dataset"), "-o", str(out), "--quiet", "--frames", "0"]) == 0
    assert "using the observations already extracted" in capsys.readouterr().err
    assert out.stat().st_size > 10_000
    # an observations file older than the dataset is not trusted
    os.utime(demo_dir / "observations.json", (1, 1))
    with pytest.raises(AssertionError, match="extracted again"):
        main(["report", str(demo_dir / "dataset"), "-o", str(out), "--quiet", "--frames", "0"])


def test_extract_says_the_lens_model_in_one_line_with_a_pointer_to_the_camera_file(tmp_path, capsys):
    ds, obs, cam = tmp_path / "ds", tmp_path / "obs.json", tmp_path / "camera.json"
    assert main(["simulate", "--images", "--plan", "rotation-sweep", "--camera-views", "8", "--out", str(ds)]) == 0
    capsys.readouterr()
    fast = ["--no-refine-camera", "--no-repredict", "--no-recover", "--quiet"]
    assert main(["extract", str(ds), "-o", str(obs), "--camera-out", str(cam), *fast]) == 0
    err = " ".join(capsys.readouterr().err.split())  # rich wraps at the console's width: compare the words
    line = err[err.index("lens model:") :]
    line = line[: line.index("(calibration.lens_model)") + len("(calibration.lens_model)")]
    assert f"in {cam}" in line and len(line) - len(str(cam)) < 130 and "dBIC" not in line, line
    # the evidence the line points to is in the camera file
    lm = json.loads(cam.read_text())["calibration"]["lens_model"]
    assert len(lm["candidates"]) > 1 and lm["chosen"] in line


def test_report_not_on_a_terminal_says_what_it_is_doing(result_doc, tmp_path):
    res = tmp_path / "r.json"
    res.write_text(json.dumps(result_doc[1]))
    r = cli("report", str(res), "-o", str(tmp_path / "r.html"), env={"I4CAL_PROGRESS_EVERY_S": "0.2"})
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert lines[0] == "report ..." and any(line.startswith("report done") for line in lines), r.stderr


def test_the_camera_scale_line_asks_to_check_the_board_only_when_far_off():
    """The demo's camera scale (about -0.16%) is what a calibrated camera gives; only beyond 0.5% is the board's
    square length worth checking."""
    from service.cli._output import scale_line

    def doc(scale: float) -> dict:
        return {"validation": {"a priori": {"vision_scale": {"scale": scale, "std": 7e-5, "n_poses": 10}}}}

    near, far = scale_line(doc(1 - 1.6e-3)), scale_line(doc(1 + 8e-3))
    assert near is not None and far is not None
    assert "-1600 +/- 70 ppm" in near and "check" not in near
    assert "check the board's square length" in far

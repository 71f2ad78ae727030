"""No traceback for a user mistake: each prints one line naming the option (or the file) and exits with status 2,
before any work is done; and the logging options."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import pytest

from i4cal.cli import main  # the whole command line (the service's commands and bench)

ROOT = Path(__file__).resolve().parents[2]


def one_line_error(capsys, argv: list[str]) -> str:
    """Run ``i4cal argv`` in this process; it must exit 2 with one line on stderr, nothing on stdout."""
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        rc = exc.code
    out, err = capsys.readouterr()
    assert rc == 2, (rc, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert out == ""
    return lines[0]


@pytest.fixture(scope="module")
def obs_file(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("mistakes") / "obs.json"
    assert main(["simulate", "--out", str(p), "--seed", "2"]) == 0
    return p


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["simulate", "--out", "x.json", "--noise", "-1"], ["--noise", "-1", ">= 0"]),
        (["simulate", "--out", "x.json", "--noise", "nan"], ["--noise", "nan"]),
        (["simulate", "--out", "x.json", "--seed", "-1"], ["--seed", "-1", ">= 0"]),
        (["simulate", "--out", "x.json", "--encoder-um", "-2"], ["--encoder-um", "-2"]),
        (["simulate", "--out", "x.json", "--board-translation-mm", "0.1", "-1", "0.3"], ["--board-translation-mm"]),
        (["report", "x", "-o", "r.html", "--workers", "0"], ["--workers", "0", ">= 1"]),
        (["extract", "DATASET", "-o", "obs.json", "--workers", "0"], ["--workers", "0"]),
        (["bench", "accuracy", "--workers", "0"], ["--workers", "0"]),
        (["serve", "--port", "70000"], ["--port", "70000"]),
        (["calibrate", "obs.json", "--method", "magic"], ["--method", "magic", "invalid choice"]),
    ],
)
def test_out_of_range_options_one_line_exit_2(capsys, tmp_path, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    line = one_line_error(capsys, argv)
    for w in words:
        assert w in line, line
    assert line.startswith("i4cal")
    assert not (tmp_path / "x.json").exists()


def test_calibrate_output_into_a_missing_or_existing_directory(capsys, tmp_path, obs_file):
    line = one_line_error(capsys, ["calibrate", str(obs_file), "-o", str(tmp_path / "no" / "such" / "r.json")])
    assert "-o/--output" in line and "does not exist" in line and str(tmp_path / "no" / "such") in line
    line = one_line_error(capsys, ["calibrate", str(obs_file), "-o", str(tmp_path)])
    assert "-o/--output" in line and "is a directory" in line


def test_simulate_into_a_directory(capsys, tmp_path):
    line = one_line_error(capsys, ["simulate", "--out", str(tmp_path)])
    assert "--out" in line and "is a directory" in line


def test_valid_edges_are_accepted(tmp_path, capsys):
    p = tmp_path / "obs.json"
    assert main(["simulate", "--out", str(p), "--seed", "0", "--noise", "0"]) == 0
    assert json.loads(p.read_text())["frames"]


def test_subprocess_one_line_and_no_usage_block():
    r = subprocess.run(
        [sys.executable, "-m", "i4cal", "simulate", "--out", "x.json", "--seed", "-1"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "i4cal simulate: error: argument --seed: -1 is not >= 0 (see i4cal simulate --help)"
    ]


@pytest.fixture
def root_logger():
    """The root logger's level and handlers, restored after the test (main() configures logging)."""
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    try:
        yield root
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)


def test_logging_options(tmp_path, root_logger):
    script = (
        "import logging, sys; from service.cli import main, configure_logging; "
        "configure_logging(*eval(sys.argv[1])); print(logging.getLogger().getEffectiveLevel())"
    )
    levels = {}
    for args in ("(0, None)", "(1, None)", "(2, None)", "(0, 'ERROR')", "(2, 'ERROR')"):
        r = subprocess.run([sys.executable, "-c", script, args], capture_output=True, text=True, cwd=ROOT)
        levels[args] = int(r.stdout)
    assert levels == {
        "(0, None)": logging.WARNING,
        "(1, None)": logging.INFO,
        "(2, None)": logging.DEBUG,
        "(0, 'ERROR')": logging.ERROR,
        "(2, 'ERROR')": logging.ERROR,
    }
    # -v before or after the command; --log-level case-insensitive; a bad level is one line
    assert main(["--log-level", "debug", "simulate", "--out", str(tmp_path / "o.json")]) == 0
    assert root_logger.level == logging.DEBUG
    assert main(["simulate", "-v", "--out", str(tmp_path / "o.json")]) == 0
    assert root_logger.level == logging.INFO
    with pytest.raises(SystemExit) as exc:
        main(["--log-level", "loud", "simulate", "--out", str(tmp_path / "o.json")])
    assert exc.value.code == 2

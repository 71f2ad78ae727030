"""The command line as a program (``python -m service.cli``, ``python -m i4cal``, the ``i4cal`` script) freezes what
is alive out of the cyclic garbage collector, whose walk at the interpreter's shutdown cost 0.1-0.2 s after every
command (docs/benchmarks.md); called in-process (:func:`service.cli.main`), the command line leaves the collector
alone."""

from __future__ import annotations

import gc
import subprocess
import sys
from importlib.metadata import entry_points

import pytest

from service.cli import main

#: runs a module as ``python -m`` does, reporting at exit how many objects the collector ignores
PROBE = (
    "import atexit, gc, runpy, sys; "
    "atexit.register(lambda: print('frozen', gc.get_freeze_count())); "
    "module, missing = sys.argv[1:]; sys.argv = ['i4cal', 'calibrate', missing]; "
    "runpy.run_module(module, run_name='__main__', alter_sys=True)"
)


@pytest.mark.parametrize("module", ["service.cli", "i4cal"])
def test_the_program_freezes_the_objects_alive_and_keeps_the_exit_code(module, tmp_path):
    missing = tmp_path / "missing.json"
    out = subprocess.run(
        [sys.executable, "-c", PROBE, module, str(missing)], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 2, out.stderr  # a user's mistake: one line, status 2, as in-process
    assert "missing.json" in out.stderr and "Traceback" not in out.stderr
    frozen = [int(line.split()[1]) for line in out.stdout.splitlines() if line.startswith("frozen ")]
    assert frozen and frozen[0] > 10_000, out.stdout  # the modules' objects: tens of thousands


def test_the_installed_script_runs_the_program():
    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "i4cal"]
    assert script.value == "i4cal.cli:run_program"


def test_main_in_process_leaves_the_collector_alone(tmp_path, capsys):
    before = gc.get_freeze_count()
    assert main(["calibrate", str(tmp_path / "missing.json")]) == 2
    assert gc.get_freeze_count() == before
    assert "missing.json" in capsys.readouterr().err

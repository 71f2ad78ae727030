"""The seam between the service and the layer above it: ``i4cal`` (the script, ``python -m i4cal``,
:func:`i4cal.cli.main`) has every service command plus ``bench``; the service's own command line
(:func:`service.cli.build_parser`, ``python -m service.cli``) has no ``bench`` and never imports :mod:`i4cal`
(also a ``lint-imports`` contract: this checks it at run time, where a lazy import inside a function counts too)."""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import service.cli
from i4cal.cli import build_parser, main


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_i4cal_has_the_service_commands_and_bench():
    service_commands = _commands(service.cli.build_parser())
    commands = _commands(build_parser())
    assert "bench" not in service_commands and "benchmark" not in service_commands
    assert set(commands) == set(service_commands) | {"bench", "benchmark"}
    assert commands["benchmark"] is commands["bench"]  # an alias: the same parser
    assert set(_commands(commands["bench"])) == {"accuracy", "check", "design", "speed"}
    # the logging options reach the added command as they reach the service's own
    assert {"-v", "--log-level"} <= set(commands["bench"]._option_string_actions)


def test_the_service_command_line_refuses_bench(capsys):
    with pytest.raises(SystemExit) as exc:
        service.cli.main(["bench"])
    assert exc.value.code == 2 and "invalid choice: 'bench'" in capsys.readouterr().err
    assert main(["bench"]) == 1 and "i4cal bench accuracy" in capsys.readouterr().out


def test_building_the_service_parser_imports_no_i4cal_module():
    code = (
        "import sys; from service.cli import build_parser; build_parser(); "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'i4cal'))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout


def test_the_installed_script_runs_the_whole_command_line():
    """The ``i4cal`` console script (pyproject's ``[project.scripts]``, installed next to this Python) has ``bench``."""
    exe = shutil.which("i4cal", path=str(Path(sys.executable).parent))
    if exe is None:  # pragma: no cover - installed by `pip install -e .`
        pytest.skip("no i4cal script next to this Python")
    r = subprocess.run([exe, "bench", "--help"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert all(f"i4cal bench {b}" in r.stdout for b in ("accuracy", "design", "speed")), r.stdout

"""``i4cal bench``: sub-commands discovered from i4cal.benchmarks; ``bench speed`` on a quick subset (real Modbus
server on loopback, real fits) through the command line, and its JSON contract. The figures themselves are
benchmarks, not asserted against targets here."""

from __future__ import annotations

import inspect
import json
import math
import subprocess
import sys

from i4cal.benchmarks.speed import SECTIONS, bench_service_module, parse_sections
from i4cal.cli import main


def test_bench_speed_quick_subset_json(tmp_path):
    out = tmp_path / "speed.json"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "i4cal",
            "bench",
            "speed",
            "--only",
            "modbus,fit",
            "--reads",
            "100",
            "--fit-repeats",
            "1",
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    assert doc["format"] == "i4cal.bench-speed/1"
    assert doc["sections"] == ["fit", "modbus"] and doc["errors"] == {}
    assert set(doc["figures"]) == {
        "fit_combined_ms",
        "fit_end_effector_ms",
        "fit_legs_ms",
        "modbus_round_trip_median_ms",
        "modbus_driver_round_trip_median_ms",
    }
    for key, f in doc["figures"].items():
        assert math.isfinite(f["value"]) and f["value"] > 0, key
        assert f["unit"] == "ms" and f["section"] in ("fit", "modbus") and f["label"]
        assert f["target"] is None and f["met"] is None
    assert len(doc["details"]["fit"]["fit_ms"]["legs"]) == 1
    assert doc["details"]["modbus"]["raw"]["n"] == 100 and doc["details"]["modbus"]["driver"]["n"] == 100
    assert doc["machine"]["cores"] >= 1 and doc["machine"]["python"] and doc["elapsed_s"] > 0
    assert "Modbus TCP loopback round trip" in r.stdout and "fit, legs method" in r.stdout  # the table


def test_sections_and_errors(capsys):
    assert parse_sections(None) == list(SECTIONS)
    assert parse_sections("modbus, memory,fit") == ["extract-calibrate", "fit", "modbus"]
    assert main(["bench", "speed", "--only", "modbus,warp"]) == 2
    err = capsys.readouterr().err
    assert "unknown benchmark section 'warp'" in err and err.count("\n") == 1
    assert main(["bench", "speed", "--only", "fit", "--fit-repeats", "0"]) == 2
    assert "--fit-repeats" in capsys.readouterr().err


def test_bench_lists_the_discovered_benchmarks(capsys):
    assert main(["bench"]) == 1
    assert "i4cal bench speed" in capsys.readouterr().out


def test_service_section_imports_the_service_benchmark():
    """The service figure comes from benchmarks/bench_service.py (imported from the checkout, not copied)."""
    mod = bench_service_module()
    assert {"paper_plan", "workers", "hz"} <= set(inspect.signature(mod.measure).parameters)
    assert bench_service_module() is mod

"""``i4cal export RESULT -o F`` and ``i4cal export --check F``: a result file of the three methods on the geometric
twin (``i4cal simulate`` then ``i4cal calibrate -o``, as a user makes one), exported as JSON and YAML, reloaded
and checked; a changed document fails the check; mistakes are one line with exit status 2."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from calib.formats.plan import make_plan
from calib.identify.export import REPRODUCE_TOL_M, load_calibration, plan_joints
from calib.model.kinematics import dkm, ikm
from calib.model.parameters import COMBINATION_NAMES, I4Parameters
from service.cli import main
from service.report.analysis import json_sha256


@pytest.fixture(scope="module")
def result_file(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("export")
    assert main(["simulate", "-o", str(d / "obs.json"), "--seed", "4"]) == 0
    assert main(["calibrate", str(d / "obs.json"), "--method", "all", "-o", str(d / "result.json"), "--json"]) == 0
    return d / "result.json"


@pytest.fixture(scope="module")
def result(result_file) -> dict:
    return json.loads(result_file.read_text(encoding="utf-8"))


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True, timeout=120)


def test_export_writes_the_document_whose_seven_reproduce_the_combinations(result_file, result, tmp_path, capsys):
    out = tmp_path / "cal.json"
    assert main(["export", str(result_file), "-o", str(out)]) == 0
    assert "combined" in capsys.readouterr().err
    doc = load_calibration(json.loads(out.read_text(encoding="utf-8")))
    entry = result["methods"]["combined"]
    assert doc.method == "combined" and doc.method_choice.startswith("recommended: load combined")
    got = doc.to_parameters().combinations()
    assert max(abs(got[k] - entry["combinations"][k]) for k in COMBINATION_NAMES) <= REPRODUCE_TOL_M
    assert doc.covariance == entry["covariance"] and doc.seven == entry["parameters_seven_completed"]
    assert doc.source.result_file == str(result_file.resolve())
    assert doc.source.result_sha256 == json_sha256(result)
    assert doc.fixed_at_nominal == ["H", "S", "q03"] and doc.run is None and doc.dataset_hash is None
    assert doc.date and doc.date.endswith("Z") and doc.software_version
    # the check: against the file it names (no --result needed), over the 'full' plan
    assert main(["export", "--check", str(out)]) == 0
    text = capsys.readouterr().out
    assert "PASS (tolerance 1e-09 m)" in text and "over 121 joint vectors of the 'full' plan" in text


def test_yaml_export_reads_back_the_same_numbers_and_checks(result_file, result, tmp_path, capsys):
    js, ym = tmp_path / "legs.json", tmp_path / "legs.yaml"
    assert main(["export", str(result_file), "-o", str(js), "--method", "legs"]) == 0
    assert main(["export", str(result_file), "-o", str(ym), "--method", "legs"]) == 0  # .yaml: YAML
    text = ym.read_text(encoding="utf-8")
    assert text.startswith("format: i4cal.calibration/1\n") and "\nunits:\n  length: m\n" in text
    a, b = json.loads(js.read_text(encoding="utf-8")), yaml.safe_load(text)
    a.pop("exported_at"), b.pop("exported_at")
    assert a == b  # every number bit for bit
    assert b["seven"] == result["methods"]["legs"]["seven"] and b["identified"] == list(b["seven"])
    other = tmp_path / "legs.txt"
    assert main(["export", str(result_file), "-o", str(other), "--method", "legs", "--format", "yaml"]) == 0
    assert yaml.safe_load(other.read_text(encoding="utf-8"))["seven"] == b["seven"]
    capsys.readouterr()
    assert main(["export", "--check", str(ym), "--result", str(result_file), "--plan", "validation", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["passed"] and rep["n_poses"] == 10 and rep["method"] == "legs" and rep["same_result"]
    assert rep["dkm_max_m"] <= 1e-9 and rep["ikm_max_m"] <= 1e-9 and rep["tolerance_m"] == 1e-9


def test_a_changed_document_fails_the_check(result_file, result, tmp_path, capsys):
    out = tmp_path / "cal.yaml"
    assert main(["export", str(result_file), "-o", str(out), "--method", "end-effector"]) == 0
    data = yaml.safe_load(out.read_text(encoding="utf-8"))
    data["seven"]["q03"] += 2e-6  # a controller's value typed with one digit wrong in the micrometres
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    capsys.readouterr()
    assert main(["export", "--check", str(bad)]) == 1
    text = capsys.readouterr().out
    assert "FAIL (tolerance 1e-09 m)" in text
    dkm_line = next(line for line in text.splitlines() if "DKM" in line)
    assert 5e-7 < float(dkm_line.split(":")[1].split()[0]) < 1e-5  # X and T move by q03 / 2, and Y, Z with it
    # a wider tolerance passes it, and says so
    assert main(["export", "--check", str(bad), "--tolerance-m", "1e-5"]) == 0
    # the model of another method is not this result's: FAIL, millimetres apart
    assert main(["export", "--check", str(out), "--result", str(result_file)]) == 0
    data = yaml.safe_load(out.read_text(encoding="utf-8"))
    data["method"] = "combined"
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(data), encoding="utf-8")
    capsys.readouterr()
    assert main(["export", "--check", str(other), "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["dkm_max_m"] > 1e-4


def _main_status(args: list[str]) -> int:
    try:
        return main(args)
    except SystemExit as exc:  # argparse's own usage errors
        return int(exc.code or 0)


def test_mistakes_are_one_line_with_status_2(result_file, result, tmp_path, capsys):
    cases = [
        (["export", str(result_file)], "give -o F"),
        (["export", "-o", str(tmp_path / "x.json")], "give RESULT|RUN"),
        (["export", str(tmp_path / "nope.json"), "-o", str(tmp_path / "x.json")], "not a run id"),
        (["export", str(result_file), "-o", str(tmp_path / "no" / "x.json")], "does not exist"),
        (["export", str(result_file), "-o", str(tmp_path / "x.json"), "--method", "nope"], "no method 'nope'"),
        (["export", str(result_file), "-o", str(tmp_path / "x.json"), "--format", "xml"], "invalid choice"),
        (["export", str(result_file), "--check", str(result_file)], "--check F takes no RESULT|RUN"),
        (["export", str(result_file), "-o", str(tmp_path / "x.json"), "--plan", "full"], "--plan goes with --check"),
        (["export", "--check", str(result_file)], "not an i4cal.calibration/1 document"),
        (["export", "--check", str(tmp_path / "none.json")], "no such document"),
        (["export", "--check", str(result_file), "--tolerance-m", "-1"], "not a finite number >= 0"),
    ]
    obs = result_file.parent / "obs.json"
    cases.append((["export", str(obs), "-o", str(tmp_path / "x.json")], "not a result file"))
    failed = json.loads(result_file.read_text(encoding="utf-8"))
    failed["methods"]["legs"] = {"converged": False, "error": "the lock phases are missing"}
    bad_result = tmp_path / "failed.json"
    bad_result.write_text(json.dumps(failed), encoding="utf-8")
    cases.append(
        (
            ["export", str(bad_result), "-o", str(tmp_path / "x.json"), "--method", "legs"],
            "'legs' did not converge in this result: the lock phases are missing",
        )
    )
    doc = tmp_path / "ok.json"
    assert main(["export", str(result_file), "-o", str(doc)]) == 0
    cases.append((["export", "--check", str(doc), "--plan", "nowhere"], "not a plan name"))
    moved = json.loads(doc.read_text(encoding="utf-8"))
    moved["source"]["result_file"] = str(tmp_path / "gone.json")
    (tmp_path / "moved.json").write_text(json.dumps(moved), encoding="utf-8")
    cases.append((["export", "--check", str(tmp_path / "moved.json")], "give --result RESULT|RUN"))
    capsys.readouterr()
    for args, what in cases:
        assert _main_status(args) == 2, args
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and what in err, (what, err)
    assert not (tmp_path / "x.json").exists()
    # as a user runs it: one line, no traceback
    res = _cli("export", "--check", str(tmp_path / "moved.json"))
    assert res.returncode == 2 and "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1


def test_the_document_loads_as_the_models_seven_parameters(result_file, tmp_path):
    """What a controller does with the file: read the seven numbers and T_per_rad, nothing else."""
    out = tmp_path / "cal.json"
    assert main(["export", str(result_file), "-o", str(out), "--method", "legs"]) == 0
    data = json.loads(out.read_text(encoding="utf-8"))
    p = I4Parameters.from_mapping({**data["seven"], "T_per_rad": data["T_per_rad"]})
    assert p.combinations() == pytest.approx(data["combinations"], abs=REPRODUCE_TOL_M)
    assert data["units"] == {"length": "m", "covariance": "m^2", "T_per_rad": "m/rad", "date": "ISO 8601 UTC"}


def _doc_blocks(lang: str) -> list[str]:
    text = (Path(__file__).resolve().parents[2] / "docs" / "export.md").read_text(encoding="utf-8")
    return [b.split("```", 1)[0] for b in text.split(f"```{lang}\n")[1:]]


@pytest.mark.skipif(not (shutil.which("jq") and shutil.which("cc")), reason="needs jq and a C compiler")
def test_the_c_example_of_the_docs_matches_the_model(result_file, tmp_path):
    """docs/export.md's header command and C functions, on an exported file: the same DKM and IKM as calib's."""
    out = tmp_path / "calibration.json"
    assert main(["export", str(result_file), "-o", str(out), "--method", "legs"]) == 0
    (jq_cmd,) = _doc_blocks("sh")
    (c_code,) = _doc_blocks("c")
    subprocess.run(jq_cmd, shell=True, cwd=tmp_path, check=True, timeout=30)
    doc = json.loads(out.read_text(encoding="utf-8"))
    params = I4Parameters.from_mapping({**doc["seven"], "T_per_rad": doc["T_per_rad"]})
    q = plan_joints(make_plan("full", I4Parameters.from_mapping(doc["nominal"])), params)
    main_c = """
#include <stdio.h>
int main(void) {
    double q[4], p[4], q2[4];
    while (scanf("%lf %lf %lf %lf", &q[0], &q[1], &q[2], &q[3]) == 4) {
        if (i4_dkm(q, p) || i4_ikm(p, q2)) { printf("unreachable\\n"); continue; }
        for (int i = 0; i < 4; i++) printf("%.17g ", p[i]);
        printf("%.17g %.17g %.17g %.17g\\n", q2[0], q2[1], q2[2], q2[3]);
    }
    return 0;
}
"""
    (tmp_path / "i4.c").write_text(c_code + main_c, encoding="utf-8")
    subprocess.run(["cc", "-O2", "-o", "i4", "i4.c", "-lm"], cwd=tmp_path, check=True, timeout=60)
    stdin = "\n".join(" ".join(repr(float(v)) for v in row) for row in q)
    res = subprocess.run([str(tmp_path / "i4")], input=stdin, capture_output=True, text=True, check=True, timeout=30)
    got = np.array([[float(v) for v in line.split()] for line in res.stdout.splitlines()])
    assert got.shape == (len(q), 8)
    pose = dkm(params, q)
    assert np.max(np.abs(got[:, :4] - pose)) < 1e-12
    assert np.max(np.abs(got[:, 4:] - ikm(params, pose))) < 1e-12
    assert np.max(np.abs(got[:, 4:] - q)) < 1e-12  # and the round trip

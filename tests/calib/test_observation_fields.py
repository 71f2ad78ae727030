"""The vision -> methods contract: the rod and board fields the image extraction writes into observations v1 are
declared, optional, typed fields of :class:`calib.formats.observations.Rod` and
:class:`~calib.formats.observations.Board`.

The documents here are built by the geometric twin and given the extraction's fields through the extraction's own
writers (:meth:`calib.vision.rods.RodMeasurement.to_dict`, :meth:`calib.vision.board.BoardPose.to_dict`) with
seeded random values: the writers' output is what is checked against the declared shapes, without rendering
images (the rendered end-to-end path is tests/calib/vision/test_extract.py's).
"""

from __future__ import annotations

import copy
import json
from typing import Any

import numpy as np
import pytest

from calib.errors import InputError
from calib.formats.observations import BOARD_FIELDS, ROD_FIELDS, Board, Observations, Rod
from calib.identify.end_effector import board_covariances
from calib.identify.intrinsics import board_sensitivities
from calib.identify.legs.joints import _rod_field
from calib.vision.board import BoardPose
from calib.vision.rods import RodMeasurement
from drivers.sim.twin import GeometricTwin


def _extracted(twin_doc: dict[str, Any], seed: int = 0) -> dict[str, Any]:
    """``twin_doc`` as the image extraction writes it: every rod and board with the extraction's fields, the
    frame-level bookkeeping and the top-level ``extraction`` block (JSON-parsed, as a file would be)."""
    rng = np.random.default_rng(seed)
    doc = copy.deepcopy(twin_doc)
    for i, f in enumerate(doc["frames"]):
        if f.get("board"):
            A = rng.normal(size=(6, 6))
            pose = BoardPose(
                R=np.asarray(f["board"]["R"]),
                t=np.asarray(f["board"]["t"]),
                rms_px=float(rng.uniform(0.05, 0.3)),
                n_corners=int(rng.integers(20, 60)),
                cov=1e-8 * (A @ A.T + np.eye(6)),
                d_intrinsics=1e-5 * rng.normal(size=(6, 8)),
            )
            f["board"] = pose.to_dict()
        for leg, rods in (f.get("legs") or {}).items():
            for j, r in enumerate(rods):
                if r is None:
                    continue
                B = rng.normal(size=(3, 3))
                m = RodMeasurement(
                    int(leg) - 1,
                    j,
                    u=np.asarray(r["u"]),
                    point=np.asarray(r["point"]),
                    h=(rng.normal(size=3), rng.normal(size=3)),
                    rms_px=(float(rng.uniform(0.1, 0.4)), float(rng.uniform(0.1, 0.4))),
                    n_points=(np.int64(rng.integers(20, 200)), np.int64(rng.integers(20, 200))),
                    plane_angle_rad=float(rng.uniform(0.01, 0.05)),
                    cov_u=1e-7 * (B @ B.T),
                    limbs_px=rng.uniform(0, 2000, size=(2, 5, 2)),
                )
                rods[j] = m.to_dict()
        f.update(missing={}, image=f"frames/{i:04d}.png", dataset_frame=i, leg_parallel_mrad={"1": 0.1})
    doc["extraction"] = {"rod_settings": {"step_px": 3.0, "edge_bias_px": 0.05}, "min_corners": 6}
    return json.loads(json.dumps(doc))


@pytest.fixture(scope="module")
def twin_doc(paper_plan) -> dict[str, Any]:
    """The geometric twin's document of the paper's plan, cut to its first 3 frames of each phase (fast)."""
    doc = json.loads(json.dumps(GeometricTwin().observations(plan=paper_plan, seed=0)))
    kept, count = [], {}
    for f in doc["frames"]:
        count[f["phase"]] = count.get(f["phase"], 0) + 1
        if count[f["phase"]] <= 3:
            kept.append(f)
    doc["frames"] = kept
    return doc


@pytest.fixture(scope="module")
def extracted_doc(twin_doc) -> dict[str, Any]:
    return _extracted(twin_doc)


def _rods(doc: dict[str, Any]):
    for i, f in enumerate(doc["frames"]):
        for leg, rods in (f.get("legs") or {}).items():
            for j, r in enumerate(rods):
                if r is not None:
                    yield i, leg, j, r


def _same(a: Any, b: Any, path: str = "") -> None:
    """``a`` and ``b`` equal as JSON content (rod directions to the normalisation's ulp). Key order is not content:
    declared fields come first on writing (``point`` after ``u``), as before the extraction's fields were declared.
    """
    assert type(a) is type(b), path
    if isinstance(a, dict):
        assert sorted(a) == sorted(b), path
        for k in a:
            _same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{path}.{k}")
    elif isinstance(a, float) and path.endswith(tuple(f".u.{k}" for k in range(3))):
        assert abs(a - b) <= 1e-15, path  # u is renormalised on reading (as before the fields were declared)
    else:
        assert a == b, path


# -- the fields are declared and typed -------------------------------------------------------------------------
def test_extraction_fields_are_declared_not_extra(extracted_doc):
    obs = Observations.from_dict(extracted_doc)
    i, leg, j, raw = next(_rods(extracted_doc))
    rod = obs.frames[i].legs[leg][j]  # type: ignore[index]
    assert not set(rod.model_extra or {}) & set(ROD_FIELDS)
    np.testing.assert_array_equal(np.asarray(rod.cov_u), raw["cov_u"])
    np.testing.assert_array_equal(np.asarray(rod.h), raw["h"])
    np.testing.assert_array_equal(np.asarray(rod.limbs_px), raw["limbs_px"])
    assert rod.n_points == raw["n_points"] and all(isinstance(n, int) for n in rod.n_points)
    assert rod.rms_px == raw["rms_px"] and rod.plane_angle_rad == raw["plane_angle_rad"]
    board = obs.frames[i].board
    assert board is not None and not set(board.model_extra or {}) & set(BOARD_FIELDS)
    assert np.asarray(board.cov).shape == (6, 6) and np.asarray(board.d_intrinsics).shape == (6, 8)
    assert board.n_corners == extracted_doc["frames"][i]["board"]["n_corners"]


def test_methods_read_the_typed_fields(extracted_doc, twin_doc):
    obs = Observations.from_dict(extracted_doc)
    data = obs.arrays("poses")
    k = int(np.nonzero(data.has_rod[:, 2, 1])[0][0])
    raw = extracted_doc["frames"][int(data.index[k])]["legs"]["3"][1]
    for name in ("h", "cov_u", "rms_px", "n_points", "limbs_px"):
        np.testing.assert_array_equal(_rod_field(obs, data, k, 2, 1, name), np.asarray(raw[name], dtype=float))
    assert board_covariances(obs, data).shape == (len(data), 6, 6)  # type: ignore[union-attr]
    assert board_sensitivities(obs, data).shape == (len(data), 6, 8)  # type: ignore[union-attr]
    plain = Observations.from_dict(twin_doc)  # a foreign document: the methods see the fields as absent
    pdata = plain.arrays("poses")
    assert _rod_field(plain, pdata, k, 2, 1, "cov_u") is None
    assert board_covariances(plain, pdata) is None and board_sensitivities(plain, pdata) is None


def test_numpy_values_are_accepted_and_written_as_lists():
    rod = Rod(
        u=np.array([0.0, 0.6, 0.8]),
        cov_u=np.eye(3) * 1e-6,
        h=np.array([[1.0, 0, 0], [0, 0, 1.0]]),
        n_points=np.array([30, 40]),
        rms_px=np.array([0.1, 0.2]),
        plane_angle_rad=np.float64(0.02),
        limbs_px=np.zeros((2, 5, 2)),
    )
    board = Board(R=np.eye(3), t=np.zeros(3), n_corners=np.int64(12), rms_px=np.float64(0.1), cov=np.eye(6))
    d = json.loads(json.dumps({"rod": rod.model_dump(mode="json"), "board": board.model_dump(mode="json")}))
    assert d["rod"]["n_points"] == [30, 40] and d["rod"]["cov_u"][2] == [0.0, 0.0, 1e-6]
    assert d["board"]["n_corners"] == 12 and "d_intrinsics" not in d["board"]


def test_every_declared_field_has_its_shape_and_unit_in_the_schema():
    for model, names in ((Rod, ROD_FIELDS), (Board, BOARD_FIELDS)):
        props = model.model_json_schema()["properties"]
        for name in names:
            desc = props[name]["description"]
            assert ("shape (" in desc or "count" in desc or "px" in desc or "rad" in desc) and ":" in desc, name
            assert name not in model.model_json_schema().get("required", []), name


# -- round trips -----------------------------------------------------------------------------------------------
def test_extracted_document_round_trips_unchanged(extracted_doc, tmp_path):
    p = tmp_path / "obs.json"
    Observations.from_dict(copy.deepcopy(extracted_doc)).save(p)
    back = json.loads(p.read_text())
    _same(extracted_doc, back)
    q = tmp_path / "again.json"  # and through a file once more
    Observations.load(p).save(q)
    _same(back, json.loads(q.read_text()))


def test_foreign_document_without_the_fields_loads_and_stays_without(twin_doc):
    obs = Observations.from_dict(copy.deepcopy(twin_doc))
    out = obs.to_dict()
    _same(twin_doc, out)  # no field added, not even as null
    for _, _, _, r in _rods(out):
        assert list(r) == ["u", "point"]
    assert all(list(f["board"]) == ["R", "t"] for f in out["frames"] if f.get("board"))
    rod = obs.frames[0].legs["1"][0]  # type: ignore[index]
    assert rod is not None and rod.cov_u is None and rod.h is None and obs.frames[0].board.cov is None  # type: ignore[union-attr]
    # a rod with no point, and a field a tool wrote as null: kept exactly as before (point null, cov_u null)
    doc = copy.deepcopy(twin_doc)
    doc["frames"][0]["legs"]["1"][0] = {"u": [0.0, 0.0, 1.0], "cov_u": None}
    assert Observations.from_dict(doc).to_dict()["frames"][0]["legs"]["1"][0] == {
        "u": [0.0, 0.0, 1.0],
        "point": None,
        "cov_u": None,
    }
    assert obs.to_dict()["frames"][0]["legs"]["1"][0] == twin_doc["frames"][0]["legs"]["1"][0]


# -- validation: the first bad field, named with its frame and leg ----------------------------------------------
_RAGGED = [[1.0, 0.0, 0.0], [0.0, 1.0], [0.0, 0.0, 1.0]]


@pytest.mark.parametrize(
    ("where", "name", "value", "text"),
    [
        ("rod", "rms_px", [0.1], "rms_px must have shape (2,)"),
        ("rod", "rms_px", [0.1, float("inf")], "non-finite"),
        ("rod", "n_points", [10, 20, 30], "n_points must have shape (2,)"),
        ("rod", "n_points", [10, -1], "greater than or equal to 0"),
        ("rod", "n_points", [10, 2.5], "valid integer"),
        ("rod", "plane_angle_rad", float("nan"), "finite number"),
        (
            "rod",
            "cov_u",
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            "cov_u must have shape (3, 3) (covariance of u), got (2, 3)",
        ),
        ("rod", "cov_u", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, float("nan")]], "cov_u contains a non-finite"),
        ("rod", "cov_u", _RAGGED, "cov_u must be an array of numbers of shape (3, 3)"),
        ("rod", "cov_u", "diag", "cov_u must be an array of numbers"),
        ("rod", "h", [[1.0, 0.0, 0.0]] * 3, "h must have shape (2, 3)"),
        ("rod", "h", [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], "two non-zero plane normals"),
        ("rod", "limbs_px", np.zeros((2, 5, 3)).tolist(), "limbs_px must have shape (2, n, 2)"),
        ("rod", "limbs_px", np.zeros((2, 1, 2)).tolist(), "at least 2 points"),
        ("board", "rms_px", -0.1, "greater than or equal to 0"),
        ("board", "n_corners", 1.5, "valid integer"),
        ("board", "cov", np.eye(6)[:5].tolist(), "cov must have shape (6, 6)"),
        ("board", "cov", np.full((6, 6), np.inf).tolist(), "cov contains a non-finite"),
        ("board", "d_intrinsics", np.zeros((5, 8)).tolist(), "d_intrinsics must have shape (6, n)"),
        ("board", "d_intrinsics", np.zeros((6, 0)).tolist(), "d_intrinsics must have shape (6, n)"),
    ],
)
def test_a_bad_field_is_named_with_its_frame_and_leg(extracted_doc, where, name, value, text):
    doc = copy.deepcopy(extracted_doc)
    frame = 5
    if where == "rod":
        doc["frames"][frame]["legs"]["3"][1][name] = value
        field = f"legs.3.1.{name}"
    else:
        doc["frames"][frame]["board"][name] = value
        field = f"board.{name}"
    with pytest.raises(InputError) as ei:
        Observations.from_dict(doc, source="obs.json")
    e = ei.value
    assert (e.file, e.frame) == ("obs.json", frame)
    assert e.field == field or e.field.startswith(field + "."), e.field  # pydantic's own checks add the item
    assert f"frame {frame}" in str(e) and text in str(e)

"""Large documents written readable by the json module's C encoder: the value of ``json.dumps(doc, indent=1)``, its
outer levels one member a line."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from calib.formats.dataset import BoardSpec, CameraSpec, DatasetWriter, LegsSpec
from calib.formats.observations import Observations
from calib.numerics.jsonio import dumps_readable
from drivers.sim.twin import GeometricTwin


@pytest.fixture(scope="module")
def observations() -> dict:
    """The twin's observations of the paper's plan: 121 frames, as ``i4cal simulate`` writes them."""
    return GeometricTwin().observations(seed=1)


def _odd_values() -> dict:
    """What the encoders must agree on besides plain numbers."""
    return {
        "floats": [0.1 + 0.2, 1e-300, -0.0, 5e-324, 1.7976931348623157e308, float("nan"), float("inf"), -float("inf")],
        "ints": [0, -1, 2**70],
        "text": ["é ü \u2603", 'quote " and \\ backslash', "\n\t"],
        "keys": {3: "int", 2.5: "float", True: "bool", None: "null"},
        "tuple": (1, (2, 3)),
        "empty": [{}, [], ""],
        "nested": {"a": [{"b": [{"c": [1, {"d": None}]}]}]},
        "bool": [True, False, None],
    }


def _canonical(text: str) -> str:
    """The parsed value, in a form where NaN equals NaN (json.loads(a) == json.loads(b) fails on NaN)."""
    return json.dumps(json.loads(text))


@pytest.mark.parametrize("depth", [0, 1, 2, 3, 6])
def test_the_readable_text_is_the_indented_texts_value(observations, depth):
    for doc in (observations, _odd_values(), [observations["frames"][:3], 1.5], {}, [], 3.25, "x"):
        new = dumps_readable(doc, depth)
        assert _canonical(new) == _canonical(json.dumps(doc, indent=1))
    assert math.isnan(json.loads(dumps_readable(_odd_values(), depth))["floats"][5])


def test_an_observations_document_takes_a_line_per_frame_member(observations):
    text = dumps_readable(observations)
    lines = text.split("\n")
    frames = observations["frames"]
    # the top level, the frames and each frame laid out: a line per member of a frame, none holding two
    assert sum(line.startswith('   "phase": ') for line in lines) == len(frames)
    assert all(line.count('"phase": ') <= 1 for line in lines)
    board = [line for line in lines if line.startswith('   "board": ')]
    assert len(board) == len(frames) and all(line.endswith(("},", "null,")) for line in board)
    assert len(lines) < len(json.dumps(observations, indent=1).split("\n")) / 10


def test_the_c_encoder_writes_it(observations, monkeypatch):
    """The json module's pure-Python encoder (what an indent runs) is not used."""

    def pure_python(*args, **kwargs):
        raise AssertionError("the pure-Python JSON encoder ran")

    monkeypatch.setattr(json.encoder, "_make_iterencode", pure_python)
    with pytest.raises(AssertionError):  # the trap works: an indent runs the pure-Python encoder
        json.dumps({"a": 1}, indent=1)
    dumps_readable(observations)


def test_observations_and_datasets_are_written_by_the_c_encoder(observations, monkeypatch, tmp_path):
    def pure_python(*args, **kwargs):
        raise AssertionError("the pure-Python JSON encoder ran")

    monkeypatch.setattr(json.encoder, "_make_iterencode", pure_python)
    obs = Observations.from_dict(observations)
    obs.save(tmp_path / "obs.json")
    text = (tmp_path / "obs.json").read_text(encoding="utf-8")
    assert _canonical(text) == json.dumps(obs.to_dict())

    w = DatasetWriter(
        tmp_path / "ds",
        camera=CameraSpec(width=64, height=48),
        board=BoardSpec(),
        legs=LegsSpec(rod_radius_m=0.004),
        nominal=GeometricTwin().geometry.nominal.as_dict(),
    )
    for k in range(3):
        w.add_frame("poses", [0.01 * k, 0.0, 0.0, 0.0], np.zeros((48, 64), np.uint8))
    w.close()
    doc = json.loads((tmp_path / "ds" / "dataset.json").read_text(encoding="utf-8"))
    assert [f["q"] for f in doc["frames"]] == [[0.01 * k, 0.0, 0.0, 0.0] for k in range(3)]

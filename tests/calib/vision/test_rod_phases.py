"""The observations carry the rods of the phases something reads (the methods: ``poses`` and the lock phases; the
report's leg residuals: ``validation``); the other frames keep their boards and say why they have no rods. The frames
that carry rods are those an extraction of every phase's rods writes, to the bit: what the methods read is unchanged,
and the rods of the ``line``, ``rotation`` and ``translation`` frames are no longer measured for nothing (71 of the
paper plan's 121 frames; docs/benchmarks.md)."""

from __future__ import annotations

import io
import json
import zipfile

import pytest

from calib.formats.observations import Observations
from calib.vision.extract import ROD_PHASES, RODS_NOT_READ, ExtractOptions, extract_dataset


@pytest.fixture(scope="module")
def both(rendered_zip, tmp_path_factory):
    root = tmp_path_factory.mktemp("rod_phases")
    zipfile.ZipFile(io.BytesIO(rendered_zip)).extractall(root)
    ds = root / "dataset"
    return (
        extract_dataset(ds, workers=1),
        extract_dataset(ds, workers=1, options=ExtractOptions(rod_phases=None)),
    )


def test_the_rods_of_the_phases_read_are_those_of_a_full_extraction(both):
    read, every = both
    frames = read.observations["frames"]
    assert {f["phase"] for f in frames} - set(ROD_PHASES)  # the plan has phases whose rods are not read
    n_read = 0
    for a, b in zip(frames, every.observations["frames"], strict=True):
        assert a["board"] == b["board"]  # every frame keeps its board
        if a["phase"] in ROD_PHASES:
            n_read += 1
            assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True), a["dataset_frame"]
        else:
            assert all(r is None for rods in a["legs"].values() for r in rods)
            assert a["missing"]["rods"] == RODS_NOT_READ
            assert any(r is not None for rods in b["legs"].values() for r in rods)  # measured when asked
    assert n_read
    Observations.from_dict(read.observations)  # a valid observations v1 document


def test_fewer_frames_are_measured_and_the_summary_says_which_phases_were_not_read(both):
    read, every = both
    assert read.summary["rods_frames"]["measured"] < every.summary["rods_frames"]["measured"]
    for phase, c in read.summary["phases"].items():
        if phase in ROD_PHASES:
            assert c["rods_total"] == 8 * c["frames"] and c["rods_not_read"] == 0
        else:
            assert c["rods_total"] == 0 and c["rods_not_read"] == 8 * c["frames"]
            assert not c["missing"]  # not counted as rods lost

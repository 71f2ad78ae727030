"""The commands that write observations (``simulate``, ``extract``) write them with the json module's C encoder,
readable: the pure-Python encoder (what ``json.dumps(..., indent=1)`` runs) is a trap here."""

from __future__ import annotations

import json

import pytest

from calib.formats.observations import Observations
from service.cli import main
from tests.calib.vision.test_board_region import N_FRAMES, sweep  # noqa: F401  (a rendered line sweep)


@pytest.fixture
def no_pure_python_encoder(monkeypatch):
    def pure_python(*args, **kwargs):
        raise AssertionError("the pure-Python JSON encoder ran")

    monkeypatch.setattr(json.encoder, "_make_iterencode", pure_python)


def _laid_out(text: str, n_frames: int) -> None:
    """The top level and the frames laid out, a line per frame member."""
    lines = text.split("\n")
    assert sum(line.startswith('   "phase": ') for line in lines) == n_frames
    assert len(lines) < 40 * n_frames


def test_simulate_writes_readable_observations(tmp_path, no_pure_python_encoder):
    out = tmp_path / "obs.json"
    assert main(["simulate", "--out", str(out), "--seed", "3"]) == 0
    obs = Observations.load(out)
    _laid_out(out.read_text(encoding="utf-8"), len(obs.frames))


def test_extract_writes_readable_observations(sweep, tmp_path, no_pure_python_encoder):  # noqa: F811
    root, _, _ = sweep
    out = tmp_path / "obs.json"
    assert main(["extract", str(root), "-o", str(out), "--workers", "1", "--quiet"]) == 0
    text = out.read_text(encoding="utf-8")
    assert len(Observations.load(out).frames) == N_FRAMES
    _laid_out(text, N_FRAMES)

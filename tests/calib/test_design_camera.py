"""A design for a camera that sees less than the simulated bench's: the sweeps and lock phases placed where that
camera sees their board, or an error saying none is."""

from __future__ import annotations

import dataclasses

import pytest

from calib.design import DesignRequest, design_plan, phase_q, visibility
from calib.errors import InputError
from calib.model.parameters import NOMINAL

REQ = DesignRequest(n_fit=4, n_lock=2, n_validation=0, with_line=False, n_candidates=60)


def _sensor(scene, width: int, height: int):
    """The twin's lens and mounting on a ``width`` x ``height`` sensor."""
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=width, height=height))


def test_the_twins_camera_keeps_the_workspace_centre(scene):
    res = design_plan(NOMINAL, scene, REQ)
    assert not any("placed about a centre moved" in n for n in res.notes), res.notes


def test_sweeps_and_lock_phases_move_to_where_a_smaller_sensor_sees_them(scene):
    """On 800 x 600 no sweep about the workspace centre keeps the board in view (before: the design failed); about
    a centre 50 mm along y every sweep and lock step's board is in view of that camera, and the note says so."""
    small = _sensor(scene, 800, 600)
    res = design_plan(NOMINAL, small, REQ)
    assert any("placed about a centre moved by (+0, +50, +0) mm" in n for n in res.notes), res.notes
    for ph in ("rotation", "translation", "poses", "lock-1", "lock-2", "lock-3", "lock-4"):
        assert visibility(small, NOMINAL, phase_q(res.plan, ph))["board"].all(), ph


def test_no_centre_within_reach_is_an_error_saying_so(scene):
    with pytest.raises(InputError, match="within 100 mm of it"):
        design_plan(NOMINAL, _sensor(scene, 640, 480), REQ)

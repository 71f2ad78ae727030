import numpy as np

from calib.formats.plan import make_plan
from calib.identify.registry import method_identifiability as identifiability
from calib.model.parameters import NOMINAL


def _q():
    return np.array([s.q for s in make_plan("pose-set", NOMINAL, seed=3).steps])


def test_combined_finds_exactly_the_paper_four():
    r = identifiability("combined", NOMINAL, _q())
    assert r["rank"] == 4
    assert r["finds_paper_four"]
    assert r["identifiable_combinations"] == ["L", "D - H", "q02 - 2 S", "q04 - 2 S - q03"]
    assert len(r["non_identifiable_directions"]) == 3


def test_end_effector_finds_the_same_four():
    r = identifiability("end-effector", NOMINAL, _q())
    assert r["rank"] == 4 and r["finds_paper_four"]


def test_legs_identify_all_seven():
    r = identifiability("legs", NOMINAL, _q())
    assert r["rank"] == 7
    assert all(r["paper_combinations_in_row_space"].values())


def test_a_single_pose_does_not_identify_four():
    r = identifiability("combined", NOMINAL, _q()[:1])
    assert r["rank"] < 4 and not r["finds_paper_four"]

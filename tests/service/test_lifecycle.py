"""The run lifecycle's state machine, exhaustively: every (state, event) pair, and what is left of a run for every
combination of what is on disk."""

from __future__ import annotations

import itertools

import pytest

from service.runs.lifecycle import (
    ACTIVE,
    FINAL,
    RESUMABLE,
    TRANSITIONS,
    IllegalTransitionError,
    RunConflictError,
    RunEvent,
    RunState,
    next_state,
    remaining_stages,
)

S, E = RunState, RunEvent

# The lifecycle written out by hand, independently of the table in the module: the test fails if either changes
# without the other.
EXPECTED = {
    (S.QUEUED, E.ACQUIRE): S.ACQUIRING,
    (S.QUEUED, E.EXTRACT): S.EXTRACTING,
    (S.QUEUED, E.CALIBRATE): S.CALIBRATING,
    (S.QUEUED, E.FINISH): S.DONE,
    (S.QUEUED, E.FAIL): S.FAILED,
    (S.QUEUED, E.ABORT): S.ABORTED,
    (S.QUEUED, E.INTERRUPT): S.INTERRUPTED,
    (S.ACQUIRING, E.EXTRACT): S.EXTRACTING,
    (S.ACQUIRING, E.FINISH): S.DONE,
    (S.ACQUIRING, E.FAIL): S.FAILED,
    (S.ACQUIRING, E.ABORT): S.ABORTED,
    (S.ACQUIRING, E.INTERRUPT): S.INTERRUPTED,
    (S.EXTRACTING, E.CALIBRATE): S.CALIBRATING,
    (S.EXTRACTING, E.FAIL): S.FAILED,
    (S.EXTRACTING, E.ABORT): S.ABORTED,
    (S.EXTRACTING, E.INTERRUPT): S.INTERRUPTED,
    (S.CALIBRATING, E.FINISH): S.DONE,
    (S.CALIBRATING, E.FAIL): S.FAILED,
    (S.CALIBRATING, E.ABORT): S.ABORTED,
    (S.CALIBRATING, E.INTERRUPT): S.INTERRUPTED,
    (S.FAILED, E.RESUME): S.QUEUED,
    (S.FAILED, E.ABORT): S.ABORTED,
    (S.INTERRUPTED, E.RESUME): S.QUEUED,
    (S.INTERRUPTED, E.ABORT): S.ABORTED,
}


@pytest.mark.parametrize(("state", "event"), list(itertools.product(RunState, RunEvent)))
def test_every_state_event_pair(state: RunState, event: RunEvent) -> None:
    if (state, event) in EXPECTED:
        assert next_state(state, event) is EXPECTED[(state, event)]
        assert next_state(state.value, event.value) is EXPECTED[(state, event)]  # as stored in the database
    else:
        with pytest.raises(IllegalTransitionError) as ei:
            next_state(state, event)
        assert isinstance(ei.value, RunConflictError)  # the routers answer 409
        assert state.value in str(ei.value) and event.value in str(ei.value)


def test_table_is_the_expected_one_and_classes_partition_the_states() -> None:
    assert TRANSITIONS == EXPECTED
    assert set(RunState) == ACTIVE | FINAL | RESUMABLE
    assert not (ACTIVE & FINAL) and not (ACTIVE & RESUMABLE) and not (FINAL & RESUMABLE)
    # final states have no way out; every other state can be ended by the user
    assert not any(s in FINAL for (s, _) in TRANSITIONS)
    assert all((s, E.ABORT) in TRANSITIONS for s in ACTIVE | RESUMABLE)
    # only a resume leaves a resumable state other than abort: nothing restarts a run on its own
    assert {e for (s, e) in TRANSITIONS if s in RESUMABLE} == {E.RESUME, E.ABORT}


def test_unknown_states_and_events_are_refused() -> None:
    for state, event in (("paused", "resume"), ("queued", "start"), ("", "")):
        with pytest.raises(IllegalTransitionError):
            next_state(state, event)


def test_only_the_acquisition_moves_and_never_with_the_frames_on_disk() -> None:
    """Every combination of what is on disk: a run with all its frames never acquires (never moves) again; stages are
    redone exactly when their output is missing; a run without methods stops after its frames."""
    for offline, plan_frames, on_disk, methods, obs, result in itertools.product(
        (False, True), (0, 5), (0, 3, 5, 6), (0, 2), (False, True), (False, True)
    ):
        r = remaining_stages(
            offline=offline,
            plan_frames=plan_frames,
            frames_on_disk=on_disk,
            methods=methods,
            observations_on_disk=obs,
            result_on_disk=result,
        )
        assert r.acquire == (not offline and on_disk < plan_frames)
        if r.acquire:
            assert r.extract == r.calibrate == (methods > 0)  # new frames: what followed them is stale
            assert r.first_event is E.ACQUIRE
            continue
        if methods == 0:
            assert (r.extract, r.calibrate) == (False, False) and r.first_event is E.FINISH
            continue
        assert r.extract == (not obs)
        assert r.calibrate == (not obs or not result)
        expected_first = E.EXTRACT if not obs else (E.CALIBRATE if not result else E.FINISH)
        assert r.first_event is expected_first
        # the first stage's event is allowed from 'queued' (where a resumed run starts)
        assert (S.QUEUED, r.first_event) in TRANSITIONS

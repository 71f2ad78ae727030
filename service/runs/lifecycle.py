"""The run lifecycle as an explicit state machine: states, the events that move a run between them, and what is
left to do when a run (re)starts, decided from what is on disk.

::

                 create                     acquire                extract               calibrate
      (none) ---------> queued ----------------> acquiring -----------> extracting ---------> calibrating
                          |  \\______________________ extract ________/^      \\                  |
                          |   \\_________________________ calibrate __________\\________________/^ |
                          |                                                                        | finish
                          +--- finish (nothing left) ---> done <---- finish (no methods) ----------+
      any active state --- fail ---> failed         --- resume ---> queued
      any active state --- abort --> aborted        (failed and interrupted runs: abort -> aborted)
      any active state --- interrupt (service stopped or crashed) ---> interrupted --- resume ---> queued

Pause is not a state: an acquiring run can be paused and resumed in place (the acquisition waits between poses).

Every transition is checked here (:func:`next_state`); the run manager applies it to the database as a
compare-and-set (the row changes only if it is still in the state the transition was computed from), so two
requests racing for one run (or two services sharing a database) cannot both move it. A transition that is not
allowed raises :class:`IllegalTransitionError` *before* anything changes: a refused resume leaves the run as it was.

:func:`remaining_stages` decides what a (re)started run still has to do from its files, never from counters that
a later stage may have overwritten: a run whose frames are all on disk never moves the robot again.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class RunState(StrEnum):
    QUEUED = "queued"
    ACQUIRING = "acquiring"
    EXTRACTING = "extracting"
    CALIBRATING = "calibrating"
    DONE = "done"
    FAILED = "failed"
    ABORTED = "aborted"
    INTERRUPTED = "interrupted"


class RunEvent(StrEnum):
    ACQUIRE = "acquire"  # the acquisition starts (the run holds the bench)
    EXTRACT = "extract"  # extraction starts (frames complete on disk)
    CALIBRATE = "calibrate"  # the fits start (observations on disk)
    FINISH = "finish"  # nothing left to do
    FAIL = "fail"  # a stage failed (device fault, bad data, internal error)
    ABORT = "abort"  # the user aborted
    INTERRUPT = "interrupt"  # the service stopped (or crashed) while the run was active
    RESUME = "resume"  # the user resumed a failed or interrupted run


S, E = RunState, RunEvent
#: Runs in these states are being executed (or about to be) by a service.
ACTIVE: frozenset[RunState] = frozenset({S.QUEUED, S.ACQUIRING, S.EXTRACTING, S.CALIBRATING})
#: Runs in these states never change again.
FINAL: frozenset[RunState] = frozenset({S.DONE, S.ABORTED})
#: Runs in these states wait for the user: resume or abort.
RESUMABLE: frozenset[RunState] = frozenset({S.FAILED, S.INTERRUPTED})

TRANSITIONS: dict[tuple[RunState, RunEvent], RunState] = {
    (S.QUEUED, E.ACQUIRE): S.ACQUIRING,
    (S.QUEUED, E.EXTRACT): S.EXTRACTING,
    (S.ACQUIRING, E.EXTRACT): S.EXTRACTING,
    (S.QUEUED, E.CALIBRATE): S.CALIBRATING,
    (S.EXTRACTING, E.CALIBRATE): S.CALIBRATING,
    (S.QUEUED, E.FINISH): S.DONE,
    (S.ACQUIRING, E.FINISH): S.DONE,
    (S.CALIBRATING, E.FINISH): S.DONE,
    **{(s, E.FAIL): S.FAILED for s in ACTIVE},
    **{(s, E.ABORT): S.ABORTED for s in ACTIVE | RESUMABLE},
    **{(s, E.INTERRUPT): S.INTERRUPTED for s in ACTIVE},
    **{(s, E.RESUME): S.QUEUED for s in RESUMABLE},
}


class RunConflictError(Exception):
    """The request conflicts with the current state (bench held, run not active...)."""


class RunNotFoundError(Exception):
    pass


class IllegalTransitionError(RunConflictError):
    """``event`` is not allowed in ``state`` (the run is left as it was)."""

    def __init__(self, state: str, event: str) -> None:
        self.state, self.event = state, event
        allowed = sorted(e.value for (s, e) in TRANSITIONS if s == state)
        hint = f"; allowed: {', '.join(allowed)}" if allowed else "; the run is final"
        super().__init__(f"cannot {event} a run that is {state}{hint}")


def next_state(state: str, event: str) -> RunState:
    """The state ``event`` leads to from ``state``.

    Raises
    ------
    IllegalTransitionError
        The event is not allowed in that state (unknown states and events included).
    """
    try:
        return TRANSITIONS[(RunState(state), RunEvent(event))]
    except (KeyError, ValueError):
        raise IllegalTransitionError(state, event) from None


@dataclass(frozen=True)
class Remaining:
    """What a (re)started run still has to do, in order."""

    acquire: bool
    extract: bool
    calibrate: bool

    @property
    def first_event(self) -> RunEvent:
        """The event that starts the first stage left (``finish`` when nothing is left)."""
        if self.acquire:
            return E.ACQUIRE
        if self.extract:
            return E.EXTRACT
        if self.calibrate:
            return E.CALIBRATE
        return E.FINISH


def remaining_stages(
    *,
    offline: bool,
    plan_frames: int,
    frames_on_disk: int,
    methods: int,
    observations_on_disk: bool,
    result_on_disk: bool,
) -> Remaining:
    """What is left of a run, from its files.

    Parameters
    ----------
    offline : bool
        The run calibrates an uploaded dataset (it never acquires).
    plan_frames : int
        Frames the run's plan records (the acquisition's total; 0 for offline runs).
    frames_on_disk : int
        Frames of the run's dataset written so far (its ``dataset.json``).
    methods : int
        Identification methods requested (0: the run records a dataset only).
    observations_on_disk : bool
        The extraction finished: its observations and summary are stored.
    result_on_disk : bool
        The fits finished: the result is stored.
    """
    acquire = not offline and frames_on_disk < plan_frames
    if acquire:
        return Remaining(True, methods > 0, methods > 0)
    if methods == 0:
        return Remaining(False, False, False)
    extract = not observations_on_disk
    return Remaining(False, extract, extract or not result_on_disk)

"""The simulated bench's shared true state: the true geometry and four simulated axes.

Every simulated device reads the same :class:`Mechanism`: the Modbus controller drives its axes
and reports their encoders, the camera renders the true mechanism at the axes' *actual* positions
(truth DKM), and the simulated operator moves the free mechanism along a truly straight ruler.

Motion is evaluated lazily from a monotonic clock (no background task): a trapezoidal profile
(speed and acceleration) from the position at the start command to the target. Encoders are
quantised to the controller's counts with a little Gaussian noise, a repeatable function of the seed,
the axis and its true position (like a real encoder's interpolation error): what a frame records does
not depend on how often, or when, the encoders were polled before it.

The simulated operator's guided line is driven by the acquisition's own sampling, not by the wall
clock (:meth:`Mechanism.begin_line`): the recorded line is the same whatever the scheduling.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from calib.model.kinematics import dkm, ikm
from drivers.sim.twin import BenchGeometry

ALARM_DRIVE_FAULT = 0x10
ALARM_NOT_HOMED = 0x20
ALARM_SOFT_LIMIT = 0x30
ALARM_HARD_LIMIT = 0x31


@dataclass
class AxisConfig:
    """Simulated axis: speeds in m/s, acceleration in m/s^2, limits in metres."""

    default_speed: float = 0.5
    accel: float = 20.0
    home_speed: float = 1.0
    home_position: float = 0.0
    soft_min: float = -0.12
    soft_max: float = 0.82
    hard_min: float = -0.15
    hard_max: float = 0.85
    in_position_m: float = 5e-6
    encoder_noise_m: float = 3e-7
    require_homing: bool = True


@dataclass
class _Profile:
    t0: float
    p0: float
    p1: float
    v: float
    a: float
    t_acc: float = 0.0
    t_total: float = 0.0
    v_peak: float = 0.0

    def __post_init__(self) -> None:
        d = abs(self.p1 - self.p0)
        if d == 0:
            return
        if d >= self.v**2 / self.a:
            self.t_acc = self.v / self.a
            self.v_peak = self.v
            self.t_total = d / self.v + self.t_acc
        else:
            self.t_acc = math.sqrt(d / self.a)
            self.v_peak = self.a * self.t_acc
            self.t_total = 2 * self.t_acc

    def at(self, t: float) -> float:
        tau = t - self.t0
        d = abs(self.p1 - self.p0)
        if tau <= 0 or d == 0:
            return self.p0
        if tau >= self.t_total:
            return self.p1
        s = np.sign(self.p1 - self.p0)
        ta, T, a, vp = self.t_acc, self.t_total, self.a, self.v_peak
        if tau < ta:
            x = 0.5 * a * tau**2
        elif tau < T - ta:
            x = 0.5 * a * ta**2 + vp * (tau - ta)
        else:
            x = d - 0.5 * a * (T - tau) ** 2
        return self.p0 + s * x

    def done(self, t: float) -> bool:
        return t - self.t0 >= self.t_total


@dataclass
class SimAxis:
    config: AxisConfig = field(default_factory=AxisConfig)
    pos: float = 0.3
    target: float = 0.3
    homed: bool = False
    free: bool = False
    alarm_code: int = 0
    homing: bool = False
    profile: _Profile | None = None
    pending_alarm: tuple[int, float] | None = None  # (code, fraction of the next move)

    @property
    def moving(self) -> bool:
        return self.profile is not None

    def update(self, now: float) -> None:
        p = self.profile
        if p is None:
            return
        if self.pending_alarm is not None and p.t_total > 0:
            code, frac = self.pending_alarm
            if now - p.t0 >= frac * p.t_total:
                self.pos = p.at(p.t0 + frac * p.t_total)
                self.profile = None
                self.pending_alarm = None
                self.alarm_code = code
                self.homing = False
                return
        x = p.at(now)
        c = self.config
        if x < c.hard_min or x > c.hard_max:
            self.pos = min(max(x, c.hard_min), c.hard_max)
            self.profile = None
            self.alarm_code = ALARM_HARD_LIMIT
            self.homing = False
            return
        self.pos = x
        if p.done(now):
            self.profile = None
            if self.homing:
                self.homing = False
                self.homed = True

    def start(self, target: float, speed: float, now: float) -> None:
        self.update(now)
        if self.alarm_code or self.free:
            return
        c = self.config
        if c.require_homing and not self.homed:
            self.alarm_code = ALARM_NOT_HOMED
            return
        if not c.soft_min <= target <= c.soft_max:
            self.alarm_code = ALARM_SOFT_LIMIT
            return
        self._go(target, speed if speed > 0 else c.default_speed, now)

    def _go(self, target: float, speed: float, now: float) -> None:
        self.target = target
        self.profile = _Profile(now, self.pos, target, speed, self.config.accel)
        if self.profile.t_total == 0:
            self.profile = None
            if self.homing:
                self._finish_home()

    def _finish_home(self) -> None:
        self.homing = False
        self.homed = True

    def home(self, now: float) -> None:
        self.update(now)
        if self.alarm_code or self.free:
            return
        self.homing = True
        self._go(self.config.home_position, self.config.home_speed, now)

    def stop(self, now: float) -> None:
        self.update(now)
        self.profile = None
        self.homing = False
        self.target = self.pos

    def reset(self, now: float) -> None:
        self.update(now)
        self.alarm_code = 0
        self.pending_alarm = None

    def set_free(self, free: bool, now: float) -> None:
        self.update(now)
        if free:
            self.profile = None
            self.homing = False
        self.free = free
        self.target = self.pos

    def in_position(self) -> bool:
        return self.profile is None and abs(self.pos - self.target) <= self.config.in_position_m and not self.free


@dataclass
class _Guide:
    t0: float
    q: np.ndarray  # (samples, 4) true joint values along the ruler
    rate_hz: float
    k: int = 0  # the mark the operator holds the ruler at
    grabbed: bool = False  # a frame was taken at mark k
    read: set[int] = field(default_factory=set)  # axes whose encoders were read since that frame


class Mechanism:
    """Shared true state of the simulated bench (thread-safe)."""

    def __init__(
        self,
        geometry: BenchGeometry | None = None,
        axis_config: AxisConfig | None = None,
        initial_q: np.ndarray | None = None,
        seed: int = 0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.geometry = geometry or BenchGeometry()
        cfg = axis_config or AxisConfig()
        q0 = np.asarray(initial_q if initial_q is not None else [0.3, 0.3, 0.3, 0.3], dtype=float)
        self.axes = [SimAxis(config=AxisConfig(**cfg.__dict__), pos=float(q), target=float(q)) for q in q0]
        self.clock = clock
        self.seed = int(seed)
        self.rng = np.random.default_rng(seed)
        self.lock = threading.RLock()
        self._guide: _Guide | None = None
        self.last_contact = self.clock()  # last request from a master (the controller's watchdog reads it)

    # -- state ----------------------------------------------------------------------------------
    def update(self) -> float:
        now = self.clock()
        with self.lock:
            self._guide_axes()
            for ax in self.axes:
                ax.update(now)
        return now

    def _guide_axes(self) -> None:
        """The free axes follow the operator's ruler at its current mark (with the lock held)."""
        g = self._guide
        if g is None:
            return
        for i, ax in enumerate(self.axes):
            if ax.free:
                ax.pos = float(g.q[g.k, i])
                ax.target = ax.pos
                c = ax.config
                if not c.hard_min <= ax.pos <= c.hard_max:
                    ax.alarm_code = ALARM_HARD_LIMIT

    def q_true(self) -> np.ndarray:
        self.update()
        with self.lock:
            return np.array([ax.pos for ax in self.axes])

    def pose_true(self, q: np.ndarray | None = None) -> np.ndarray:
        """True end-effector pose (X, Y, Z, T) of the true mechanism (truth DKM)."""
        return dkm(self.geometry.truth, self.q_true() if q is None else q)

    def encoder_m(self, axis: int) -> float:
        """Encoder reading (metres, before quantisation to counts) of axis 0..3.

        The noise is a repeatable function of (seed, axis, true position): reading the same still axis
        twice gives the same value, and the value does not depend on the number of reads before.
        While the operator guides the line, a read of an axis already read since the last frame means
        the acquisition has moved on to its next sample: the operator first moves the ruler to the next
        mark (:meth:`begin_line`).
        """
        with self.lock:
            g = self._guide
            if g is not None and g.grabbed:
                if axis in g.read and g.k < len(g.q) - 1:
                    g.k += 1
                    g.grabbed = False
                    g.read = set()
                    self._guide_axes()
                elif g.grabbed:
                    g.read.add(axis)
            ax = self.axes[axis]
            pos = ax.pos
        sigma = ax.config.encoder_noise_m
        if not sigma:
            return pos
        bits = int(np.float64(pos).view(np.uint64))
        rng = np.random.default_rng([self.seed, axis, bits >> 32, bits & 0xFFFFFFFF])
        return pos + float(rng.normal(0.0, sigma))

    def frame_taken(self) -> None:
        """The camera took a frame (the frame server calls this after rendering): during a guided line, the
        operator holds the ruler at its mark until the encoders have been read back after this frame."""
        with self.lock:
            g = self._guide
            if g is not None:
                g.grabbed = True
                g.read = set()

    # -- operator -------------------------------------------------------------------------------
    def begin_line(self, start_pose, end_pose, samples: int, rate_hz: float) -> None:
        """The simulated operator guides the free end-effector along a truly straight ruler.

        The ruler has ``samples`` marks (poses of the line, true geometry IKM). The operator holds it at
        mark k until the camera has taken a frame there (:meth:`frame_taken`) and the encoders have been
        read back after it (every axis read once); the next encoder read of an axis already read is the
        acquisition's next sample, and the operator has moved to mark k + 1 by then. The acquisition reads
        the encoders, grabs, reads them again (stillness check) per sample, so sample k records mark k
        whatever the scheduling (a wall-clock operator, pose k during [k, k+1) / rate_hz, made the
        recorded line depend on how late each sample came: up to one mark, 10 mm, apart between runs).
        ``rate_hz`` is the acquisition's pace, which the operator follows. Deterministic as long as the
        acquisition is the only client polling the encoders during the line, and each of its encoder reads
        reads every axis once (the Modbus driver with one unit per axis, the serial ASCII driver).
        """
        s = np.linspace(0.0, 1.0, int(samples))[:, None]
        poses = (1 - s) * np.asarray(start_pose, float) + s * np.asarray(end_pose, float)
        q = ikm(self.geometry.truth, poses)
        with self.lock:
            self._guide = _Guide(self.clock(), np.atleast_2d(q), float(rate_hz))
        self.update()

    def end_line(self) -> None:
        self.update()
        with self.lock:
            self._guide = None

    # -- faults ---------------------------------------------------------------------------------
    def inject_alarm(self, axis: int, code: int = ALARM_DRIVE_FAULT, at_fraction: float = 0.5) -> None:
        """Axis 0..3 goes into alarm ``code`` part-way through its next (or current) move."""
        with self.lock:
            self.axes[axis].pending_alarm = (int(code), float(at_fraction))

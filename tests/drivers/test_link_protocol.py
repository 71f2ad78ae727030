"""The seam between the motion logic and a protocol: :class:`drivers.devices.axes.AxisController` over any
:class:`drivers.devices.links.AxisLink`, and the URI scheme registry of :mod:`drivers.acquisition.config`.

The link here is written in the test (axes in memory that move at the commanded speed): no hardware exists that
speaks it, which is the point: the controller's safety behaviour (limits before any request, alarms, a confirmed
stop on error or cancellation, plausible readings) holds over a link that knows nothing of it. The Modbus and ASCII
links are tested against the simulated controller in test_modbus*.py, test_link_faults.py, test_serial_ascii.py.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from collections.abc import Sequence

import numpy as np
import pytest

from calib.errors import InputError
from drivers.acquisition import config
from drivers.acquisition.config import (
    BenchConfig,
    open_actuators,
    open_camera,
    open_operator,
    register_actuators_scheme,
)
from drivers.devices.axes import AxisController
from drivers.devices.interfaces import Actuators, AxisStatus
from drivers.devices.links import Command
from drivers.devices.modbus import ModbusActuators, ModbusLink, ModbusLinkSettings
from drivers.devices.serial_ascii import SerialAsciiActuators, SerialAsciiLink
from drivers.errors import AlarmError, DeviceError, LimitError, ProtocolError, StopNotConfirmedError


class MemoryLink:
    """An AxisLink over ``n`` axes in memory, each moving at its commanded speed (m/s) from the last start."""

    endpoint = "memory"

    def __init__(self, n: int = 3, *, reads_every_axis: bool = False) -> None:
        self.n_axes, self.reads_every_axis = n, reads_every_axis
        self.stats = {"requests": 0}
        self.q0, self.target, self.v, self.t0 = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
        self.homed, self.stuck, self.alarm = False, False, [0] * n
        self.sent: list[tuple] = []

    def q(self) -> np.ndarray:
        d = self.target - self.q0
        return self.q0 + np.sign(d) * np.minimum(np.abs(d), self.v * (time.monotonic() - self.t0))

    async def open(self) -> None:
        self.sent.append(("open",))

    async def close(self) -> None:
        self.sent.append(("close",))

    async def read_axes(self, axes: Sequence[int]) -> dict[int, AxisStatus]:
        self.stats["requests"] += 1
        q = self.q()
        moving = [self.stuck or q[i] != self.target[i] for i in range(self.n_axes)]
        return {
            i: AxisStatus(True, moving[i], not moving[i], bool(self.alarm[i]), self.homed, False, self.alarm[i], q[i])
            for i in (range(self.n_axes) if self.reads_every_axis else axes)
        }

    async def start_move(self, targets_m: np.ndarray, speeds_m_s: np.ndarray) -> None:
        self.stats["requests"] += 1
        self.sent.append(("move", tuple(targets_m), tuple(speeds_m_s)))
        self.q0, self.target, self.v = self.q(), np.array(targets_m), np.array(speeds_m_s)
        self.t0 = np.full(self.n_axes, time.monotonic())

    async def control(self, axis: int, command: Command | None, *, free: bool, urgent: bool = False) -> None:
        self.stats["requests"] += 1
        self.sent.append((command, axis, free, urgent))
        if command == "stop":
            self.q0[axis] = self.target[axis] = self.q()[axis]
        self.homed |= command == "home"
        self.alarm[axis] = 0 if command == "reset" else self.alarm[axis]


def controller(link: MemoryLink, **kw) -> AxisController:
    opts = dict(speed_m_s=1.0, accel_m_s2=100.0, poll_s=0.001, move_timeout_margin_s=0.5, stop_deadline_s=0.3)
    return AxisController(link, **{**opts, **kw})


def stops(link: MemoryLink) -> list[int]:
    return sorted(c[1] for c in link.sent if c[0] == "stop" and c[3])  # urgent stops, by axis


@pytest.mark.parametrize("every_axis", [False, True])
async def test_controller_moves_over_a_minimal_link(every_axis):
    link = MemoryLink(reads_every_axis=every_axis)
    act = controller(link)
    assert isinstance(act, Actuators)
    async with act:
        await act.home()
        target = np.array([0.30, 0.15, 0.0])
        q = await act.move(target)
        np.testing.assert_allclose(q, target, atol=1e-12)
        moves = [c for c in link.sent if c[0] == "move"]
        assert len(moves) == 1
        np.testing.assert_allclose(moves[0][2], [1.0, 0.5, 1e-3])  # scaled to arrive together (floor v/1000)
        r0 = link.stats["requests"]
        st = await act.status()
        assert link.stats["requests"] - r0 == (1 if every_axis else 3)  # one read of every axis, or one per axis
        assert st.homed and not st.moving and act.stats is link.stats
    assert link.sent[-1] == ("close",)


async def test_limits_and_workspace_refused_before_any_request():
    link = MemoryLink()

    def reach(q):
        from calib.errors import UnreachableError

        if q.sum() > 0.5:
            raise UnreachableError("too far")

    act = controller(link, workspace_check=reach)
    async with act:
        n0 = len(link.sent), link.stats["requests"]
        with pytest.raises(LimitError, match="q1 = 900.000 mm is outside the soft limits"):
            await act.move([0.9, 0.0, 0.0])
        with pytest.raises(LimitError, match="outside the workspace"):
            await act.move([0.3, 0.3, 0.0])
        assert (len(link.sent), link.stats["requests"]) == n0  # nothing went out


async def test_alarm_mid_move_stops_every_axis():
    link = MemoryLink()
    async with controller(link) as act:
        task = asyncio.create_task(act.move([0.5, 0.5, 0.5]))
        await asyncio.sleep(0.05)
        link.alarm[1] = 0x30
        with pytest.raises(AlarmError, match="axis 2 in alarm, code 0x30") as ei:
            await task
        assert ei.value.axis == 2 and stops(link) == [0, 1, 2]
        q1 = link.q()
        await asyncio.sleep(0.02)
        np.testing.assert_array_equal(link.q(), q1)  # stopped, short of the target
        assert np.all(q1 < 0.4)


async def test_cancelled_move_stops_every_axis():
    link = MemoryLink()
    async with controller(link) as act:
        task = asyncio.create_task(act.move([0.5, 0.5, 0.5]))
        await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert stops(link) == [0, 1, 2]
        q1 = link.q()
        await asyncio.sleep(0.02)
        np.testing.assert_array_equal(link.q(), q1)


async def test_a_stop_not_read_back_is_not_confirmed():
    link = MemoryLink()
    async with controller(link) as act:
        link.stuck = True  # every axis keeps reading moving
        t0 = time.monotonic()
        with pytest.raises(StopNotConfirmedError, match="motion may NOT have stopped") as ei:
            await act.move([0.2, 0.2, 0.2], timeout_s=0.05)
        assert ei.value.axes == (1, 2, 3) and "did not complete within 0.05 s" in str(ei.value)
        assert time.monotonic() - t0 < 0.05 + act.stop_deadline_s + 0.5


class DeafOnceLink(MemoryLink):
    """Acknowledges every axis' first stop without acting on it (a lost frame answered by a copy of an earlier
    stop's echo, a drive busy): the reply proves that something answered, not that the drive stopped."""

    def __init__(self, n: int = 3) -> None:
        super().__init__(n)
        self.ignored: set[int] = set()

    async def control(self, axis: int, command: Command | None, *, free: bool, urgent: bool = False) -> None:
        if command == "stop" and axis not in self.ignored:
            self.ignored.add(axis)
            self.stats["requests"] += 1
            self.sent.append((command, axis, free, urgent))
            return
        await super().control(axis, command, free=free, urgent=urgent)


async def test_a_stop_acknowledged_but_not_obeyed_is_sent_again():
    link = DeafOnceLink()
    async with controller(link, stop_deadline_s=1.0) as act:
        task = asyncio.create_task(act.move([0.5, 0.5, 0.5]))
        await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task  # the stop is confirmed: no StopNotConfirmedError replaces the cancellation
        q1 = link.q()
        await asyncio.sleep(0.02)
        np.testing.assert_array_equal(link.q(), q1)  # stopped, short of the target
        assert np.all(q1 < 0.4)
        assert stops(link) == [0, 0, 1, 1, 2, 2]  # each axis: the ignored stop, then the one obeyed


async def test_an_implausible_reading_moves_nothing():
    link = MemoryLink()
    async with controller(link, max_speed_m_s=1.0) as act:
        link.q0[0] = 0.3  # 300 mm away from the last reading a moment ago: more than 1 m/s allows
        with pytest.raises(ProtocolError, match="axis 1: implausible position 300.000 mm read from memory"):
            await act.move([0.1, 0.0, 0.0])
        assert not [c for c in link.sent if c[0] == "move"]
        link.q0[1] = 7.0  # beyond the soft limits + margin, whatever the time
        await asyncio.sleep(0.01)
        with pytest.raises(ProtocolError, match="axis 2: implausible position 7 m"):
            await act.read_encoders()


async def test_free_drives_are_refused_a_move():
    link = MemoryLink()
    async with controller(link) as act:
        await act.set_free(True)
        assert [c for c in link.sent if c[0] is None] == [(None, i, True, False) for i in range(3)]
        assert all(a.free for a in (await act.status()).axes)
        with pytest.raises(DeviceError, match="drives are free"):
            await act.move([0.1, 0.1, 0.1])
        await act.reset_alarms()
        assert link.sent[-1] == ("reset", 2, True, False)  # the free bit stays with every control word


def test_both_drivers_are_the_controller_over_a_link():
    """Composed, not inherited: the ASCII driver is no Modbus driver; both are the one controller."""
    mb = ModbusActuators(ModbusLinkSettings(port=1))
    sa = SerialAsciiActuators("socket://127.0.0.1:1", speed_m_s=0.1, backoff_s=0.05)
    assert isinstance(mb, AxisController) and isinstance(mb.link, ModbusLink) and mb.n_axes == 4
    assert isinstance(sa, AxisController) and isinstance(sa.link, SerialAsciiLink) and sa.n_axes == 4
    assert not isinstance(sa, ModbusActuators)
    assert sa.link.backoff_s == sa.backoff_s == 0.05 and sa.speed_m_s == 0.1
    assert mb.endpoint == "127.0.0.1:1" and sa.endpoint == "socket://127.0.0.1:1 (ASCII)"


# -- the URI scheme registry ------------------------------------------------------------------------------------------
def bench(actuators: str = "modbus+tcp://127.0.0.1:5020", camera: str = "sim://127.0.0.1:5022", **kw) -> BenchConfig:
    return BenchConfig.model_validate({"actuators": {"uri": actuators}, "camera": {"uri": camera}, **kw})


@pytest.fixture
def registry(monkeypatch):
    """The registries as they are, restored after the test."""
    for reg in (config._ACTUATORS, config._CAMERAS, config._OPERATORS):
        monkeypatch.setattr(reg, "_factories", dict(reg._factories))


def test_unknown_schemes_name_the_uri_and_the_known_ones():
    with pytest.raises(InputError, match=r"unknown actuators URI scheme 'canopen' in 'canopen://x'.*modbus\+tcp"):
        open_actuators(bench("canopen://x"))
    with pytest.raises(InputError, match=r"unknown camera URI scheme 'gige' in 'gige://1'.*genicam, v4l2, replay, sim"):
        open_camera("gige://1")
    with pytest.raises(InputError, match=r"unknown operator URI 'robot://arm' \(console, sim\)"):
        open_operator(bench(operator={"uri": "robot://arm"}))
    assert {"modbus+tcp", "modbus+rtu", "modbus+rtu+tcp", "serial", "serial+tcp"} <= set(config.actuators_schemes())


def test_a_registered_scheme_opens_its_backend(registry):
    link = MemoryLink(4)
    seen = []

    def factory(cfg, uri, workspace_check):
        seen.append((uri.scheme, uri.host, uri.port, uri.query, workspace_check))
        return controller(link, limits=cfg.soft_limits())

    register_actuators_scheme("memory", factory)
    act = open_actuators(bench("memory://here:7?x=1"))
    assert isinstance(act, AxisController) and act.link is link
    assert seen == [("memory", "here", 7, {"x": "1"}, None)]
    with pytest.raises(ValueError, match="'memory' is already registered"):
        register_actuators_scheme("memory", lambda *a: None)
    register_actuators_scheme("memory", lambda *a: "other", replace=True)
    assert open_actuators(bench("memory://")) == "other"


def test_a_factory_named_by_module_is_imported_when_first_opened(registry, tmp_path, monkeypatch):
    (tmp_path / "i4cal_test_backend.py").write_text(
        "def open_it(c, uri):\n    return ('camera', uri.path, c.timeout_s)\n", encoding="utf-8"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    config.register_camera_scheme("plug", "i4cal_test_backend:open_it")
    assert "i4cal_test_backend" not in sys.modules
    assert open_camera("plug:///dev/x") == ("camera", "/dev/x", 2.0)
    assert "i4cal_test_backend" in sys.modules
    monkeypatch.delitem(sys.modules, "i4cal_test_backend")
    config.register_camera_scheme("gone", "no_such_module_here:open_it")
    with pytest.raises(InputError, match="camera URI scheme 'gone': cannot load its backend"):
        open_camera("gone://x")


def test_opening_the_simulated_bench_imports_no_simulator():
    """The sim:// camera and operator and the simulated controller's Modbus URI are opened by production code
    that never imports drivers.sim (a fresh interpreter: this one has imported it for the fixtures)."""
    code = (
        "import sys\n"
        "from drivers.acquisition.config import BenchConfig, open_actuators, open_camera, open_operator\n"
        "cfg = BenchConfig.model_validate({'actuators': {'uri': 'modbus+rtu+tcp://127.0.0.1:5021'},"
        " 'camera': {'uri': 'sim://127.0.0.1:5022'}, 'operator': {'uri': 'sim://127.0.0.1:5022'}})\n"
        "devices = open_actuators(cfg), open_camera(cfg), open_operator(cfg)\n"
        "print(*(type(d).__name__ for d in devices))\n"
        "print(sorted(m for m in sys.modules if m.startswith('drivers.sim')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split("\n")[:2] == ["ModbusActuators SimCamera SimOperator", "[]"], out.stdout + out.stderr

"""The bench file's ``[actuators]`` section reaches the Modbus driver's two settings objects, key by key.

``drivers.acquisition.config.open_actuators`` builds :class:`drivers.devices.modbus.ModbusLinkSettings` (how the link
reaches the
controller) and :class:`drivers.devices.axes.AxisSettings` (how the axes move) from the section and the URI; nothing is
connected here (the driver is only built), so no server is needed.
"""

from __future__ import annotations

import dataclasses

import pytest

from calib.errors import InputError
from drivers.acquisition.config import BenchConfig, open_actuators
from drivers.devices.axes import AxisSettings
from drivers.devices.modbus import ModbusActuators, ModbusLinkSettings

#: every key of ``[actuators]`` the driver reads, off its default
SECTION = {
    "speed_m_s": 0.07,
    "accel_m_s2": 0.9,
    "timeout_s": 0.4,
    "retries": 5,
    "poll_s": 0.004,
    "settle_s": 0.1,
    "in_position_m": 3e-5,
    "home_timeout_s": 45.0,
    "stop_deadline_s": 1.5,
    "late_reply_guard_s": 0.7,
    "max_speed_m_s": 0.4,
    "plausibility_margin_m": 0.02,
    "vary_reads": False,
    "duplicate_window_s": 0.08,
    "watchdog_s": 0.0,
}


def _driver(uri: str, **section) -> ModbusActuators:
    cfg = BenchConfig.model_validate(
        {"actuators": {"uri": uri, **SECTION, **section}, "camera": {"uri": "sim://127.0.0.1:1"}}
    )
    act = open_actuators(cfg)
    assert isinstance(act, ModbusActuators)
    return act


def test_every_actuators_key_reaches_the_link_or_the_axes():
    act = _driver("modbus+tcp://10.0.0.7:1502")
    link = act.modbus
    assert (link.transport, link.host, link.port) == ("tcp", "10.0.0.7", 1502)
    assert (link.timeout_s, link.retries, link.late_reply_guard_s, link.vary_reads) == (0.4, 5, 0.7, False)
    assert link.safety.duplicate_window_s == 0.08
    axes = AxisSettings(**{f.name: getattr(act, f.name) for f in dataclasses.fields(AxisSettings)})
    assert axes == AxisSettings(
        speed_m_s=0.07,
        accel_m_s2=0.9,
        poll_s=0.004,
        settle_s=0.1,
        in_position_m=3e-5,
        home_timeout_s=45.0,
        stop_deadline_s=1.5,
        max_speed_m_s=0.4,
        plausibility_margin_m=0.02,
    )


def test_the_uri_chooses_the_transport_and_its_query_the_timeout():
    rtu = _driver("modbus+rtu:///dev/ttyUSB3?baudrate=57600&timeout=0.25").modbus
    assert (rtu.transport, rtu.serial_port, rtu.baudrate, rtu.timeout_s) == ("rtu", "/dev/ttyUSB3", 57600, 0.25)
    gateway = _driver("modbus+rtu+tcp://192.168.1.20:4001").modbus
    assert (gateway.transport, gateway.host, gateway.port) == ("rtu-tcp", "192.168.1.20", 4001)


def test_a_serial_uri_without_a_device_is_refused_naming_the_field():
    with pytest.raises(InputError, match="serial device path") as exc:
        _driver("modbus+rtu://")
    assert exc.value.field == "actuators.uri"


def test_the_settings_defaults_are_the_bench_files():
    """A bench file that sets nothing but the URI gives the settings objects' own defaults (one set of defaults)."""
    cfg = BenchConfig.model_validate({"actuators": {"uri": "modbus+tcp://h:502"}, "camera": {"uri": "sim://h:1"}})
    act = open_actuators(cfg)
    assert isinstance(act, ModbusActuators)
    link_defaults = ModbusLinkSettings()
    assert (act.modbus.timeout_s, act.modbus.retries, act.modbus.vary_reads) == (
        link_defaults.timeout_s,
        link_defaults.retries,
        link_defaults.vary_reads,
    )
    for f in dataclasses.fields(AxisSettings):
        if f.name != "max_speed_m_s":  # None in the settings: 5 x speed_m_s on the controller
            assert getattr(act, f.name) == f.default, f.name

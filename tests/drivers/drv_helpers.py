"""Helpers shared by the driver tests (imported as a top-level module: tests/drivers is on sys.path)."""

from __future__ import annotations

import dataclasses

import numpy as np

from drivers.devices.axes import AxisSettings
from drivers.devices.modbus import ModbusActuators, ModbusLinkSettings
from drivers.sim.bench import SimBench
from drivers.sim.mechanism import AxisConfig


class TinyRenderer:
    """A fake renderer: a small image whose pixels encode the true q (mm) it was asked to draw."""

    def render(self, q_true, pose_true):
        img = np.zeros((24, 32), np.uint8)
        img[0, :4] = np.clip(np.round(np.asarray(q_true) * 100), 0, 255).astype(np.uint8)
        img[1:, :] = 7
        return img


FAST = AxisConfig(default_speed=10.0, accel=1000.0, home_speed=10.0, encoder_noise_m=3e-7)


def make_modbus(bench: SimBench, transport: str = "tcp", **kw) -> ModbusActuators:
    host, port = bench.tcp_address
    if transport == "rtu-tcp":
        port = int(bench.rtu_url.rsplit(":", 1)[1])
    opts = dict(
        transport=transport,
        host=host,
        port=port,
        speed_m_s=2.0,
        accel_m_s2=40.0,
        timeout_s=0.2,
        retries=2,
        backoff_s=0.01,
        poll_s=0.001,
        move_timeout_margin_s=0.5,
    )
    opts.update(kw)
    return modbus_actuators(**opts)


def modbus_actuators(**kw) -> ModbusActuators:
    """A Modbus driver from flat keywords: each one goes to the settings object that has the field
    (:class:`ModbusLinkSettings` or :class:`AxisSettings`); the rest (limits, nominal, workspace_check, safety) to
    the driver."""
    link_fields = {f.name for f in dataclasses.fields(ModbusLinkSettings)}
    axis_fields = {f.name for f in dataclasses.fields(AxisSettings)}
    link = ModbusLinkSettings(**{k: v for k, v in kw.items() if k in link_fields})
    axes = AxisSettings(**{k: v for k, v in kw.items() if k in axis_fields})
    rest = {k: v for k, v in kw.items() if k not in link_fields and k not in axis_fields}
    return ModbusActuators(link, axes, **rest)

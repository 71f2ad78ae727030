"""A configurable Modbus register map for linear axes (four by default, the I4's), and the default one.

Default map (``RegisterMap()``), per axis, unit id 1..4, holding registers:

==========  ===========================================================================
0-1         target position, int32, high word first, 1 count = 1 um
2-3         speed, int32, counts/s
4           control: bit 0 start, bit 1 stop, bit 2 home, bit 3 alarm reset (self-clearing);
            bit 4 free (drive de-energised while set, encoder still read)
5           status (read-only): bit 0 ready, bit 1 moving, bit 2 in position, bit 3 alarm, bit 4 homed
6-7         actual (encoder) position, int32
8           alarm code (read-only)
==========  ===========================================================================

Variants: all axes on one unit id at register offsets (``axes=[{unit: 1, offset: 0}, {unit: 1,
offset: 10}, ...]``), low word first (``word_order = "little"``), another scale, a move started by
writing the target (``start_mode = "target_write"``), other bit numbers.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class AxisAddress(BaseModel):
    model_config = ConfigDict(frozen=True)
    unit: int = Field(ge=0, le=247)
    offset: int = Field(0, ge=0)


def _default_axes() -> list[AxisAddress]:
    return [AxisAddress(unit=i, offset=0) for i in (1, 2, 3, 4)]


class ControlBits(BaseModel):
    model_config = ConfigDict(frozen=True)
    start: int = 0
    stop: int = 1
    home: int = 2
    reset: int = 3
    free: int = 4


class StatusBits(BaseModel):
    model_config = ConfigDict(frozen=True)
    ready: int = 0
    moving: int = 1
    in_position: int = 2
    alarm: int = 3
    homed: int = 4


class RegisterMap(BaseModel):
    """Where each quantity of an axis lives (register addresses relative to the axis' offset)."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    axes: list[AxisAddress] = Field(default_factory=_default_axes, min_length=1, max_length=16)
    target: int = 0
    speed: int = 2
    control: int = 4
    status: int = 5
    actual: int = 6
    alarm_code: int = 8
    word_order: Literal["big", "little"] = "big"
    signed: bool = True
    counts_per_m: float = Field(1e6, gt=0, description="position counts per metre (1 count = 1 um)")
    speed_counts_per_m: float = Field(1e6, gt=0, description="speed register counts per m/s")
    start_mode: Literal["control_bit", "target_write"] = "control_bit"
    control_bits: ControlBits = ControlBits()
    status_bits: StatusBits = StatusBits()

    # -- addresses ------------------------------------------------------------------------
    def addr(self, axis: int, field: str) -> tuple[int, int]:
        """``(unit id, absolute register address)`` of a field of axis 0..n-1."""
        a = self.axes[axis]
        return a.unit, a.offset + getattr(self, field)

    @property
    def span(self) -> int:
        """Number of registers an axis occupies (from its offset)."""
        return max(
            self.target + 2, self.speed + 2, self.control + 1, self.status + 1, self.actual + 2, self.alarm_code + 1
        )

    # -- values ---------------------------------------------------------------------------
    def to_regs32(self, value: int) -> list[int]:
        v = int(value)
        if self.signed:
            if not -(2**31) <= v < 2**31:
                raise ValueError(f"{v} does not fit in int32")
            v &= 0xFFFFFFFF
        elif not 0 <= v < 2**32:
            raise ValueError(f"{v} does not fit in uint32")
        hi, lo = (v >> 16) & 0xFFFF, v & 0xFFFF
        return [hi, lo] if self.word_order == "big" else [lo, hi]

    def from_regs32(self, regs: list[int]) -> int:
        a, b = int(regs[0]) & 0xFFFF, int(regs[1]) & 0xFFFF
        hi, lo = (a, b) if self.word_order == "big" else (b, a)
        v = (hi << 16) | lo
        if self.signed and v >= 2**31:
            v -= 2**32
        return v

    def m_to_counts(self, m: float) -> int:
        return round(m * self.counts_per_m)

    def counts_to_m(self, c: int) -> float:
        return c / self.counts_per_m

    def speed_to_counts(self, v_m_s: float) -> int:
        return round(v_m_s * self.speed_counts_per_m)

    def counts_to_speed(self, c: int) -> float:
        return c / self.speed_counts_per_m

    def bit(self, kind: Literal["control", "status"], name: str) -> int:
        bits = self.control_bits if kind == "control" else self.status_bits
        return 1 << getattr(bits, name)


DEFAULT_MAP = RegisterMap()

#: Alarm code of the simulated controller's communication watchdog (a move stopped for want of requests).
ALARM_WATCHDOG = 0x50

#: Alarm codes of the simulated controller (a real drive has its own; the driver reports them as given).
ALARM_TEXT = {
    0x10: "following error / drive fault",
    0x20: "move refused: axis not homed",
    0x30: "target outside the controller's soft limits",
    0x31: "hard limit reached",
    0x40: "overload",
    0x50: "communication watchdog: no request from the master during a move; stopped",
}

"""Implementations of :class:`calib.mechanism.Mechanism`: the I4 (adapter) and a linear Delta (docs/mechanisms.md)."""

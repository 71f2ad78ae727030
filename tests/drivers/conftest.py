"""Fixtures for driver tests: an in-process simulated bench on 127.0.0.1 (real sockets), fast speeds."""

from __future__ import annotations

import pytest
from drv_helpers import FAST, TinyRenderer

from drivers.sim.bench import SimBench


@pytest.fixture
async def bench():
    b = SimBench(port=0, axis_config=FAST, renderer=TinyRenderer(), seed=1)
    await b.start()
    try:
        yield b
    finally:
        await b.stop()

"""The console operator: a person at the bench, prompted on the terminal.

The same person guides the free end-effector along the ruler during a ``line`` step (:class:`drivers.devices.interfaces.
Operator`) and holds the calibration board up for the camera's intrinsics (:class:`drivers.devices.interfaces.
BoardPresenter`, ``i4cal camera calibrate``). The simulated bench's operator is :class:`drivers.devices.cameras.sim.
SimOperator` (``sim://HOST:PORT``).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from calib.camera.views import BoardPlacement

from drivers.errors import AbortedError


class ConsoleOperator:
    """A person prompted on the terminal (stdin): Enter when ready; ``q`` then Enter stops a board session."""

    def __init__(self, read: Callable[[], str] = input) -> None:
        self._read = read

    async def begin_line(self, start_pose, end_pose, samples: int, rate_hz: float) -> None:
        print(
            f"Drives are free. Guide the end-effector along the ruler from {np.round(start_pose, 4).tolist()} "
            f"to {np.round(end_pose, 4).tolist()} in about {samples / rate_hz:.0f} s, starting when you press "
            "Enter.",
            flush=True,
        )
        await asyncio.to_thread(self._read)

    async def end_line(self) -> None:
        print("Line recorded; the drives will be re-energised.", flush=True)

    async def present_board(self, placement: BoardPlacement) -> None:
        """Wait for the person to hold the board as asked (``placement.text``, which the session has said on the
        console) and press Enter; the frame is grabbed then.

        Raises
        ------
        AbortedError
            The person typed ``q`` (or the input ended).
        """
        print("Press Enter to grab (q then Enter to stop).", flush=True)
        try:
            answer = await asyncio.to_thread(self._read)
        except EOFError:
            raise AbortedError("the operator's input ended") from None
        if answer.strip().lower() in ("q", "quit", "stop"):
            raise AbortedError("stopped by the operator")

    async def board_done(self) -> None:
        print("Board views done: put the board back on the end-effector.", flush=True)

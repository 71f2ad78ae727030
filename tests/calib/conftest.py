"""Fixtures shared by the experiment-design tests: the simulated bench's scene and image-level noise model."""

from __future__ import annotations

import pytest

from service.design import twin_image_noise, twin_scene


@pytest.fixture(scope="session")
def scene():
    """The camera, its mounting, the board and the rods of the simulated bench (calib.design.Scene)."""
    return twin_scene()


@pytest.fixture(scope="session")
def noise():
    """The image-level twin's noise model (calib.design.ImageNoise)."""
    return twin_image_noise()

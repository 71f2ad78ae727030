"""Shared fixtures: seeded simulated observations on the geometric twin."""

from __future__ import annotations

import numpy as np
import pytest

from calib.observations import Observations
from calib.parameters import NOMINAL
from calib.plan import make_plan
from drivers.sim.twin import GeometricTwin, NoiseSpec


@pytest.fixture(scope="session")
def paper_plan():
    return make_plan("full", NOMINAL, seed=0)


@pytest.fixture(scope="session")
def noise_free_obs(paper_plan) -> tuple[Observations, GeometricTwin]:
    twin = GeometricTwin(noise=NoiseSpec.zero())
    return Observations.from_dict(twin.observations(plan=paper_plan, seed=0)), twin


@pytest.fixture(scope="session")
def noisy_obs(paper_plan) -> tuple[Observations, GeometricTwin]:
    twin = GeometricTwin()
    return Observations.from_dict(twin.observations(plan=paper_plan, seed=7)), twin


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


#: Session fixtures that are costly to build (a rendered dataset, a PostgreSQL cluster): with pytest-xdist
#: (``--dist loadgroup``) every test using one of them runs on the same worker, so each is built once per run.
XDIST_GROUPS = {"rendered_zip": "rendered", "postgres_url": "postgres"}
#: The project's module-scoped fixtures (Monte-Carlo studies, rendered datasets) are grouped the same way, named by
#: fixture and module: one built in a module fixture ran once per worker that got one of its tests (2 x 115 s).
SHARED_SCOPES = ("module",)


def _shared_fixture_group(item) -> str | None:
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return None
    for name in info.names_closure:
        defs = info.name2fixturedefs.get(name)
        if not defs:
            continue
        fd = defs[-1]
        if fd.scope in SHARED_SCOPES and str(fd.baseid).startswith("tests"):
            return f"{name}@{fd.baseid}"
    return None


def pytest_collection_modifyitems(config, items):
    for item in items:
        group = next((g for f, g in XDIST_GROUPS.items() if f in getattr(item, "fixturenames", ())), None)
        group = group or _shared_fixture_group(item)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))

"""The second mechanism end to end: a linear Delta on a three-axis simulated Modbus bench.

Real parts: the bench file (TOML, ``[actuators] axes = 3``) read by ``drivers.config.load_bench``, the simulated
controller as a real pymodbus server on loopback, the real Modbus driver (``open_actuators``) moving the three axes
and reading them back. The pose plan is validated before anything moves (soft limits, reachability through the
Delta's IKM) and the driver refuses a target outside the Delta's workspace (its DKM). Simulated because it cannot
exist here: the camera, replaced by the Delta's geometric twin, which observes the target on the plate at the
simulated drives' TRUE positions with the twin's camera noise. The generic end-effector fit then recovers the
Delta's true identifiable combinations within their reported standard deviations.
"""

from __future__ import annotations

import numpy as np
import pytest

from calib.errors import InputError
from calib.mechanism import joint_targets
from calib.mechanisms import get_mechanism
from calib.mechanisms.linear_delta import DeltaWorkspace
from calib.methods.generic_end_effector import fit_end_effector
from drivers.config import load_bench, open_actuators
from drivers.errors import LimitError
from drivers.sim.controller import SimController
from drivers.sim.delta_twin import DeltaTwin

BENCH = """
name = "linear-delta-sim"
[actuators]
uri = "modbus+tcp://127.0.0.1:{port}"
axes = 3
speed_m_s = 10.0
accel_m_s2 = 1000.0
timeout_s = 0.5
poll_s = 0.001
[actuators.limits]
q_min = [0.0, 0.0, 0.0]
q_max = [0.75, 0.75, 0.75]
[camera]
uri = "sim://127.0.0.1:9"  # not opened: the Delta's camera is its geometric twin
"""


async def test_linear_delta_end_to_end_over_modbus(tmp_path) -> None:
    delta = get_mechanism("linear-delta")
    nominal = delta.nominal()
    twin = DeltaTwin(seed=7)
    sim = twin.sim_mechanism()
    assert len(sim.axes) == 3

    # the bench file names three axes; the register map (units 1..3) and the soft limits follow from it
    (tmp_path / "probe.toml").write_text(BENCH.format(port=1), encoding="utf-8")
    regmap = load_bench(tmp_path / "probe.toml").register_map()
    assert [a.unit for a in regmap.axes] == [1, 2, 3]
    controller = SimController(sim, regmap, watchdog_s=0.5)
    _, port = await controller.serve_tcp("127.0.0.1", 0)
    try:
        bench_file = tmp_path / "bench.toml"
        bench_file.write_text(BENCH.format(port=port), encoding="utf-8")
        cfg = load_bench(bench_file)
        lim = cfg.actuators.limits

        # the plan, validated before anything moves: an unreachable pose is refused, naming it
        poses = DeltaWorkspace().grid()
        with pytest.raises(InputError, match="frame 3.*not reachable"):
            joint_targets(delta, nominal, np.vstack([poses[:3], [[0.4, 0.0, -0.3]]]), lim.q_min, lim.q_max)
        q_targets = joint_targets(delta, nominal, poses, lim.q_min, lim.q_max)

        act = open_actuators(cfg, workspace_check=lambda q: delta.dkm(nominal, q))
        assert act.n_axes == 3
        await act.connect()
        try:
            await act.home()
            writes = controller.writes
            with pytest.raises(LimitError, match="outside the workspace.*legs cannot meet"):
                await act.move([0.75, 0.0, 0.0])  # within the soft limits, out of the Delta's reach
            with pytest.raises(LimitError, match="needs 3 finite values"):
                await act.move([0.3, 0.3, 0.3, 0.3])
            assert controller.writes == writes  # nothing was sent

            q_read, q_true, points = [], [], []
            for q in q_targets:
                q_read.append(await act.move(q))
                q_true.append(sim.q_true())
                points.append(twin.observe(q_true[-1]))  # the camera sees the TRUE mechanism
        finally:
            await act.close()
    finally:
        await controller.shutdown()

    Qr, Qt, Y = np.array(q_read), np.array(q_true), np.array(points)
    # what the driver read back is the drives' true position, to the counts (1 um) and the encoder noise
    assert np.max(np.abs(Qr - Qt)) < 0.5e-6 + 5 * twin.noise.encoder_m
    assert np.max(np.abs(Qr - q_targets)) <= act.in_position_m

    res = fit_end_effector(delta, Qr, Y, twin.noise.camera_m)
    truth = np.array(list(delta.identifiable_combinations(twin.truth).values()))
    est = np.array(list(res.combinations.values()))
    std = np.array(list(res.combinations_std.values()))
    start = np.array(list(delta.identifiable_combinations(nominal).values()))
    # 4.5 sigma for each of 12 combinations: a false alarm has a chance below 1e-4
    assert np.all(np.abs(est - truth) < 4.5 * std), (est - truth) / std
    assert np.max(np.abs(start - truth) / std) > 5  # the nominal geometry is far off in these units
    # the residuals' scale matches the twin's camera noise: chi-square with dof = 3 x 39 - 12, 4 sigma
    assert res.dof == 3 * len(poses) - 12 and res.rank == 12
    assert abs(res.sigma0**2 - 1) < 4 * np.sqrt(2 / res.dof)
    # the std follow from the noise: 39 poses, 0.1-0.25 mm camera noise give sub-millimetre combinations
    assert np.all(std < 1e-3) and np.all(std > 1e-5)


def test_bench_file_axis_count_defaults_to_four_and_is_checked(tmp_path) -> None:
    # the published bench files are unchanged: four axes, units 1..4, four soft limits, the I4's nominal check
    cfg = load_bench("deploy/bench-sim.toml")
    assert cfg.actuators.axes == 4
    assert [a.unit for a in cfg.register_map().axes] == [1, 2, 3, 4]
    assert len(cfg.soft_limits().q_min) == 4
    # three axes: default limits one per axis; explicit lists must match
    p = tmp_path / "b.toml"
    p.write_text('[actuators]\nuri = "modbus+tcp://127.0.0.1:1"\naxes = 3\n[camera]\nuri = "sim://h:1"\n')
    cfg3 = load_bench(p)
    assert cfg3.soft_limits().q_min == (-0.10,) * 3 and len(cfg3.register_map().axes) == 3
    assert open_actuators(cfg3).nominal is None  # type: ignore[attr-defined]  # the I4 check does not apply
    p.write_text(
        '[actuators]\nuri = "modbus+tcp://127.0.0.1:1"\naxes = 3\n[actuators.limits]\nq_min = [0.0, 0.0, 0.0, 0.0]\n'
        '[camera]\nuri = "sim://h:1"\n'
    )
    with pytest.raises(InputError, match=r"b.toml, field 'actuators': .*limits.q_min has 4 values for 3 axes"):
        load_bench(p)
    p.write_text(
        '[actuators]\nuri = "modbus+tcp://127.0.0.1:1"\naxes = 2\n[actuators.register_map]\n'
        'axes = [{unit = 1}, {unit = 2}, {unit = 3}]\n[camera]\nuri = "sim://h:1"\n'
    )
    with pytest.raises(InputError, match="register_map.axes lists 3 axes for 2"):
        load_bench(p)
    p.write_text('[actuators]\nuri = "serial+tcp://127.0.0.1:1"\naxes = 3\n[camera]\nuri = "sim://h:1"\n')
    with pytest.raises(InputError, match="serial ASCII protocol drives four axes"):
        open_actuators(load_bench(p))

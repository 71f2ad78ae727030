"""`i4cal sim-bench` as a process, read and moved by a standard Modbus client through the documented map;
`i4cal acquire` killed mid-run: motion stops (controller watchdog), the dataset is readable to the last frame."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from calib.formats.dataset import Dataset

I4CAL = [sys.executable, "-c", "import sys; from service.cli import main; sys.exit(main())"]


def _free_base() -> int:
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            p = s.getsockname()[1]
        if p > 60000:
            continue
        ok = True
        for q in (p + 1, p + 2):
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", q))
                except OSError:
                    ok = False
        if ok:
            return p
    raise RuntimeError("no free ports")


@pytest.fixture
def sim_bench_process():
    port = _free_base()
    proc = subprocess.Popen(
        [*I4CAL, "sim-bench", "--port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    uris = {}
    try:
        t_end = time.monotonic() + 20
        while len(uris) < 4 and time.monotonic() < t_end:
            line = proc.stdout.readline()
            if not line:
                break
            k, _, v = line.strip().partition(" = ")
            uris[k] = v
        assert uris.get("actuators") == f"modbus+tcp://127.0.0.1:{port}", uris
        yield port, uris
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_standard_client_moves_the_sim_bench(sim_bench_process):
    from pymodbus.client import ModbusTcpClient

    port, uris = sim_bench_process
    assert uris["camera"] == f"sim://127.0.0.1:{port + 2}"
    c = ModbusTcpClient("127.0.0.1", port=port, timeout=1)
    assert c.connect()
    try:
        c.write_registers(4, [1 << 2], device_id=1)  # home axis 1
        for _ in range(200):
            st = c.read_holding_registers(5, count=1, device_id=1).registers[0]
            if st & (1 << 4) and not st & (1 << 1):
                break
            time.sleep(0.01)
        target = 123456  # um
        speed = 500000  # um/s
        c.write_registers(0, [target >> 16, target & 0xFFFF, speed >> 16, speed & 0xFFFF, 1], device_id=1)
        for _ in range(200):
            st = c.read_holding_registers(5, count=1, device_id=1).registers[0]
            if st & (1 << 2) and not st & (1 << 1):
                break
            time.sleep(0.01)
        regs = c.read_holding_registers(6, count=2, device_id=1).registers
        assert abs(((regs[0] << 16) | regs[1]) - target) <= 3
        assert c.write_registers(5, [0], device_id=1).isError()  # status is read-only
    finally:
        c.close()


def test_killed_acquisition(sim_bench_process, tmp_path):
    from pymodbus.client import ModbusTcpClient

    port, _ = sim_bench_process
    bench = Path(__file__).resolve().parents[2] / "deploy" / "bench-sim.toml"
    text = (
        bench.read_text()
        .replace("127.0.0.1:5020", f"127.0.0.1:{port}")
        .replace("127.0.0.1:5022", f"127.0.0.1:{port + 2}")
    )
    (tmp_path / "bench.toml").write_text(text)
    out = tmp_path / "ds"
    proc = subprocess.Popen(
        [
            *I4CAL,
            "acquire",
            "--bench",
            str(tmp_path / "bench.toml"),
            "--plan",
            "full",
            "--out",
            str(out),
            "--no-progress",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        t_end = time.monotonic() + 60
        while time.monotonic() < t_end:
            try:
                if len(json.loads((out / "dataset.json").read_text())["frames"]) >= 3:
                    break
            except (OSError, ValueError):
                pass
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(5)
    finally:
        if proc.poll() is None:
            proc.kill()
    ds = Dataset.open(out)
    assert len(ds.frames) >= 3
    for i in range(len(ds.frames)):
        assert ds.load_image(i).size > 0
    time.sleep(0.8)  # the controller's watchdog (0.5 s without a request during a move) stops the axes
    c = ModbusTcpClient("127.0.0.1", port=port, timeout=1)
    assert c.connect()
    try:
        for unit in (1, 2, 3, 4):
            assert not c.read_holding_registers(5, count=1, device_id=unit).registers[0] & (1 << 1)
    finally:
        c.close()

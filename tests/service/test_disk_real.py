"""A run on a real full disk: the service's data directory on a small tmpfs that fills up mid-acquisition (frames
and SQLite alike refuse with ENOSPC / ``database or disk is full``, no failpoint).

Mounting a tmpfs needs privileges: the scenario runs in a child process inside a new user and mount namespace
(``unshare -rm``), where an unprivileged user may mount a tmpfs when the kernel allows user namespaces
(``kernel.unprivileged_userns_clone``, AppArmor's ``apparmor_restrict_unprivileged_userns``). Where it does not,
the test is skipped, saying so; ``test_disk.py`` covers the same behaviour with the disk-full failpoint.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TMPFS_BYTES = 24 * 1024 * 1024
#: what the ballast file leaves free on the tmpfs: about two frames
LEFT_FREE_BYTES = 600_000


def _namespace_tmpfs_available(where: Path) -> str | None:
    """None when ``unshare -rm`` can mount a tmpfs here, else why not."""
    if shutil.which("unshare") is None:
        return "no unshare(1)"
    where.mkdir(parents=True, exist_ok=True)
    p = subprocess.run(
        ["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o size=1m tmpfs '{where}'"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    if p.returncode != 0:
        return f"no tmpfs in a user namespace here ({p.stderr.strip() or p.returncode})"
    return None


def test_a_real_full_disk_fails_the_run_and_it_resumes_when_space_returns(tmp_path):
    mnt = tmp_path / "mnt"
    why = _namespace_tmpfs_available(mnt)
    if why:
        pytest.skip(f"{why}: test_disk.py covers this with the disk-full failpoint")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("I4CAL_DISK_FULL", None)
    cmd = f"mount -t tmpfs -o size={TMPFS_BYTES} tmpfs '{mnt}' && exec '{sys.executable}' '{__file__}' '{mnt}'"
    p = subprocess.run(["unshare", "-rm", "sh", "-c", cmd], capture_output=True, text=True, timeout=240, env=env)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    assert p.returncode == 0 and lines, p.stdout[-2000:] + p.stderr[-4000:]
    out = json.loads(lines[-1][len("RESULT ") :])
    run = out["failed"]
    assert run["state"] == "failed" and run["error"].startswith("disk full"), out
    assert "during the acquisition" in run["error"], out
    assert 3 <= run["done"] < out["total"], out
    assert out["new_run"][0] == 507 and out["resume_while_full"][0] == 507, out
    assert out["db_state_after_space"] == "failed", out
    assert out["resume"] == 202, out
    assert out["after"] == {"state": "done", "done": out["total"], "frames_on_disk": out["total"]}, out


# -- the scenario, run inside the namespace -----------------------------------------------------------------------
class _NoiseRenderer:
    """Frames PNG cannot compress (512 x 512 bytes of noise): the tmpfs fills in a few frames."""

    def __init__(self) -> None:
        import numpy as np

        self.rng = np.random.default_rng(5)

    def render(self, q_true, pose_true):
        import numpy as np

        return self.rng.integers(0, 256, (512, 512), dtype=np.uint8)


async def _scenario(root: Path) -> dict:
    from drivers.sim.bench import SimBench
    from drivers.sim.mechanism import AxisConfig
    from tests.service.conftest import AUTH, make_settings, start_service, wait_state

    out: dict = {}
    axes = AxisConfig(default_speed=10.0, accel=1000.0, home_speed=10.0)
    async with SimBench(port=0, renderer=_NoiseRenderer(), seed=1, axis_config=axes) as sim:
        # the free-space check would refuse this run on 24 MiB: expected frames of 1 byte, nothing kept free
        svc = await start_service(make_settings(root, sim, min_free_bytes=0, frame_bytes=1), sim)
        c = svc.client
        try:
            r = await c.post("/api/v1/runs", json={"plan": "full", "methods": []}, headers=AUTH)
            assert r.status_code == 202, r.text
            rid, out["total"] = r.json()["id"], r.json()["progress"]["total"]
            async with asyncio.timeout(60):
                while (await c.get(f"/api/v1/runs/{rid}")).json()["progress"]["done"] < 3:
                    await asyncio.sleep(0.01)
            st = os.statvfs(root)
            with open(root / "ballast", "wb") as f:
                f.write(b"\1" * (st.f_bavail * st.f_frsize - LEFT_FREE_BYTES))
                f.flush()
                os.fsync(f.fileno())
            run = await wait_state(c, rid, timeout=30)
            out["failed"] = {"state": run["state"], "error": run["error"], "done": run["progress"]["done"]}
            r = await c.post("/api/v1/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
            out["new_run"] = [r.status_code, r.json()]
            r = await c.post(f"/api/v1/runs/{rid}/resume", headers=AUTH)
            out["resume_while_full"] = [r.status_code, r.json()]
            (root / "ballast").unlink()
            db = svc.app.state.manager.db
            from service.db import Run

            async with asyncio.timeout(10):
                while True:
                    with db.session() as s:
                        state = s.get(Run, rid).state
                    if state != "acquiring":
                        break
                    await asyncio.sleep(0.1)
            out["db_state_after_space"] = state
            r = await c.post(f"/api/v1/runs/{rid}/resume", headers=AUTH)
            out["resume"] = r.status_code
            run = await wait_state(c, rid, timeout=60)
            ds = json.loads((root / "data" / "runs" / rid / "dataset" / "dataset.json").read_text())
            out["after"] = {"state": run["state"], "done": run["progress"]["done"], "frames_on_disk": len(ds["frames"])}
        finally:
            await c.aclose()
            await svc.stop()
    return out


if __name__ == "__main__":  # inside the namespace, the tmpfs mounted at sys.argv[1]
    print("RESULT " + json.dumps(asyncio.run(_scenario(Path(sys.argv[1])))), flush=True)

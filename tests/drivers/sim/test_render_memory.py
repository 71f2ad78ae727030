"""The image-level twin reuses a frame's freed temporaries instead of page-faulting them in again for every frame
(drivers/sim/_memory.py, applied when the renderer is imported). Counted in minor page faults, not timed: before,
each 1024x768 frame faulted ~98,600 pages (~400 MB) in, which cost about as much system CPU as the rendering."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = """
import resource
import numpy as np
from calib.model.kinematics import dkm
from drivers.sim.render import BenchRenderer
from drivers.sim.twin import BenchGeometry

g = BenchGeometry()
r = BenchRenderer(g)
q = np.array([0.3, 0.3, 0.3, 0.3])
pose = dkm(g.truth, q)
r.render(q, pose, np.random.default_rng(0))  # the first frame grows the heap to its peak
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for k in range(3):
    r.render(q, pose, np.random.default_rng(k + 1))
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 3)
"""


def test_frames_after_the_first_do_not_fault_their_memory_in_again():
    # a fresh process: nothing else in it has tuned the allocator
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, check=True, timeout=120)
    per_frame = float(out.stdout.strip())
    assert per_frame < 2_000, per_frame  # ~98,600 with glibc's default thresholds

"""One thread per numerical library in a pool's worker process.

A process pool already runs one worker per core. OpenBLAS (behind numpy and SciPy) and OpenCV each start their own
thread per core on top of that, in every worker: the threads only contend for the same cores, and OpenBLAS's spin
while they wait (measured: an extraction with two workers on 2 cores 12% more CPU; the test suite's numerical tests
about 25%). :func:`single_threaded_worker` is the pools' initialiser.
"""

from __future__ import annotations


def single_threaded_worker() -> None:
    """Limit this process to one BLAS/OpenMP thread (threadpoolctl, whatever library numpy was built with) and one
    OpenCV thread. Called first in a pool worker; the parent process keeps its own settings."""
    import cv2
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    cv2.setNumThreads(1)

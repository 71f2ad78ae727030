"""One thread per numerical library in a pool's worker process.

A process pool already runs one worker per core. OpenBLAS (behind numpy and SciPy) and OpenCV each start their own
thread per core on top of that, in every worker: the threads only contend for the same cores, and OpenBLAS's spin
while they wait, which costs CPU time (more than a tenth of an extraction's) and buys no speed.

How the limit is set depends on how the worker starts:

* a **spawned** worker (a fresh interpreter: the benchmarks' pools) calls :func:`single_threaded_worker` as its
  initialiser;
* a **forked** worker (the extraction pool) must not touch OpenCV's thread pool: the child has a copy of the
  parent's pool state but none of its threads, and ``cv2.setNumThreads`` there waits forever for them (a parent that
  has rendered with OpenCV's threads before forking makes its children hang). The parent forks its workers
  inside :func:`forking_single_threaded` instead: the settings are lowered around the fork, the children inherit
  them, and the parent's own are restored.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator


def single_threaded_worker() -> None:
    """Limit this freshly started (spawned) process to one BLAS/OpenMP thread (threadpoolctl, whatever library numpy
    was built with) and one OpenCV thread. Never in a forked child (see the module's docstring)."""
    import cv2
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    cv2.setNumThreads(1)


@contextlib.contextmanager
def forking_single_threaded() -> Iterator[None]:
    """Processes forked inside the block run one BLAS/OpenMP and one OpenCV thread; this process's own settings are
    restored when the block ends (while it runs, this process is single-threaded too).

    Yields
    ------
    None
        Control, inside the block.
    """
    import cv2
    from threadpoolctl import threadpool_limits

    n_cv = cv2.getNumThreads()
    with threadpool_limits(limits=1):
        cv2.setNumThreads(1)
        try:
            yield
        finally:
            cv2.setNumThreads(n_cv)


@contextlib.contextmanager
def single_threaded() -> Iterator[None]:
    """This process runs one BLAS/OpenMP and one OpenCV thread inside the block (an extraction with one worker, which
    is this process alone, as each worker of a pool runs); its own settings are restored when the block ends.

    Yields
    ------
    None
        Control, inside the block.
    """
    with forking_single_threaded():  # the same limits; nothing is forked here
        yield

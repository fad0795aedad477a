"""One thread per process in the compiled kernels the testbed calls: studies parallelise
by process (workers), and a kernel's own threads then only compete with them.

OpenCV parallelises its filters over a thread pool whose threads wait actively between
calls: measured on this 2-core machine, a 33-tap Gaussian of a 480 x 544 float32 image took
0.61 ms of wall time either way, and 1.24 ms of CPU time with OpenCV's default 2 threads
(0.85 ms with 1 thread, 0.61 ms with threading off). BLAS threads are set through the
environment before numpy is imported (``studies.cli.SINGLE_THREAD_VARS``).
"""

from __future__ import annotations

import os

_done = False


def single_threaded_kernels() -> None:
    """Turn OpenCV's threading off in this process, unless ``OPENCV_FOR_THREADS_NUM`` is
    set (the user's choice then stands). Cheap after the first call."""
    global _done
    if _done:
        return
    _done = True
    if os.environ.get("OPENCV_FOR_THREADS_NUM"):
        return
    import cv2

    cv2.setNumThreads(0)

"""Process settings for the testbed's work: one thread per process in the compiled kernels
it calls, and the imports frozen out of the garbage collector's scans.

Studies parallelise by process (workers), and a kernel's own threads then only compete
with them.

OpenCV parallelises its filters over a thread pool whose threads wait actively between
calls: measured on this 2-core machine, a 33-tap Gaussian of a 480 x 544 float32 image took
0.61 ms of wall time either way, and 1.24 ms of CPU time with OpenCV's default 2 threads
(0.85 ms with 1 thread, 0.61 ms with threading off). BLAS threads are set through the
environment before numpy is imported (``studies.numerics``).

A process that imports numpy, scipy, trimesh, numba and pybullet holds a few hundred
thousand long-lived objects, which every full collection of the garbage collector scans
again; :func:`freeze_work_modules` (the command line) and :func:`freeze_worker` (study
workers) move them out of its scans once (``gc.freeze``).
"""

from __future__ import annotations

import contextlib
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


#: the modules a simulation and an estimate import (the rest of a run's imports follow
#: from them)
WORK_MODULES = ("studies.main_job", "testbed.simulate", "testbed.fluoroscope", "testbed.robot",
                "testbed.sweep", "testbed.ct", "testbed.operator", "testbed.dataset",
                "reglib.pipeline", "reglib.register", "reglib.markers", "reglib.contours",
                "reglib.xray_contours", "reglib.surface")

_frozen = False


def freeze_work_modules() -> None:
    """Import :data:`WORK_MODULES` and move every object alive now (the libraries' and ours:
    modules, classes, numba's and scipy's tables) into the garbage collector's permanent
    generation (``gc.freeze``), so that the full collections during the work do not scan
    them again. Measured on ``testbed run`` (experiment2), alternating runs: 4.61 s of CPU
    on average with the freeze against 4.90 s without (5 runs each), and 4.63 against 4.94 s
    with the freeze alone against the same imports without it (3 each); the collector's own
    time, timed by its callbacks, is ~0.15 s a run either way (objects made after the
    freeze, such as numba's tables at its first compiled call, are still scanned), so part
    of the gain is presumably the caches and pages the scans no longer disturb.
    For processes that do the work and exit: the command line (see :func:`freeze_worker`
    for a study's workers)."""
    import importlib

    # the imports make mostly long-lived objects: the young collections go on (they free
    # the imports' cyclic garbage), the full ones wait (each scanned every object made so
    # far, ~45 ms, and _freeze's collect scanned them all again, ~45 ms, freeing about 40
    # objects); then what is alive is frozen as it is
    with hold_full_collections():
        for name in WORK_MODULES:
            importlib.import_module(name)
        _freeze(collect=False)


@contextlib.contextmanager
def hold_full_collections():
    """No full (generation 2) collection inside the block: the young generations are
    collected as usual."""
    import gc

    saved = gc.get_threshold()
    gc.set_threshold(saved[0], saved[1], 1 << 30)
    try:
        yield
    finally:
        gc.set_threshold(*saved)


def freeze_before_exit() -> None:
    """At the end of a command-line process's work (:func:`freeze_work_modules`'s
    processes): what the work left alive is frozen too, so that the interpreter's last full
    collection at exit does not scan it (measured ~45 ms on ``testbed run``); the process
    exits next, nothing is lost but that scan."""
    import gc

    if _frozen:
        gc.freeze()


def freeze_worker() -> None:
    """In a study's worker process (not in the process that started the study), after its
    first trial: what that trial imported and built to stay (modules, numba's and scipy's
    tables, compiled kernels) is frozen out of the collector's scans, as the command line
    does (:func:`freeze_work_modules`); the trial's garbage is collected first."""
    import multiprocessing

    if multiprocessing.parent_process() is not None:
        _freeze()


def _freeze(collect: bool = True) -> None:
    global _frozen
    if _frozen:
        return
    import gc

    if collect:
        gc.collect()
    gc.freeze()
    _frozen = True


def quiet_pybullet() -> None:
    """Import pybullet with standard error silenced at the file-descriptor level: its C
    module prints a build-time banner there on import, which would make an error report two
    lines (and a study's workers printed it each). A no-op when pybullet is already imported
    or not installed."""
    import sys

    if "pybullet" in sys.modules:
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real descriptor 2 (embedded interpreters)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        try:
            import pybullet  # noqa: F401
        except ImportError:
            pass
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)

"""The numeric environment of a testbed process: the same seed gives the same numbers on
every machine. Set before numpy is first imported (its BLAS and its SIMD dispatch read the
environment when they load); this module imports nothing heavy.

Two things made a seed's result depend on the machine:

- **BLAS threads.** A multithreaded BLAS sums in an order that depends on its thread count
  (the default run: mTRE 0.518 mm on one thread, 0.538 mm on two). Studies parallelise by
  process, so one thread per process costs nothing.
- **The CPU's instruction set.** OpenBLAS picks its kernels for the CPU it finds, and
  numpy dispatches some loops to AVX-512 where the CPU has it; both round differently from
  the AVX2 code. The X-ray snake's decisions (where it resamples, which edge it settles on)
  flip on such rounding, so on a Zen 4 (AVX-512) machine the default run gave mTRE
  0.3405 mm (466 / 408 / 560 contour pixels in three views) where the AVX2 machines gave
  0.3041 mm (471 / 416 / 556); with OpenBLAS's Haswell kernels and numpy's AVX-512 loops
  off it gave 0.3040983232826933 mm, the AVX2 machines' figure to the last bit. So on an
  x86-64 CPU with AVX2 and FMA (every x86 server since 2013) the process uses the AVX2
  code: ``OPENBLAS_CORETYPE=Haswell`` and numpy's AVX-512 targets listed in
  ``NPY_DISABLE_CPU_FEATURES``. Another CPU (ARM, or x86 without AVX2) keeps its own code
  and may give other last digits.

Every variable is a default: one the environment already sets stands.
"""

from __future__ import annotations

import os
import platform

#: BLAS/OpenMP thread counts set to 1
SINGLE_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
#: numpy's dispatch targets that use AVX-512, by the names of numpy >= 2.4 and of the
#: releases before (a name numpy does not dispatch would be warned of at its import)
NUMPY_AVX512_TARGETS = {
    "new": ("X86_V4", "AVX512_ICL", "AVX512_SPR"),
    "old": ("AVX512F", "AVX512_SKX", "AVX512_CLX", "AVX512_CNL", "AVX512_ICL", "AVX512_SPR"),
}


def cpuinfo_field(name: str, path: str = "/proc/cpuinfo") -> str | None:
    """The first value of a field of Linux's CPU list (``"flags"``, ``"model name"``), or
    None where there is no such field or file."""
    try:
        with open(path, encoding="ascii", errors="replace") as f:
            for line in f:
                key, sep, value = line.partition(":")
                if sep and key.strip() == name:
                    return value.strip()
    except OSError:
        pass
    return None


def cpu_flags(path: str = "/proc/cpuinfo") -> frozenset[str]:
    """The CPU's feature flags as Linux lists them (empty where there is no such file)."""
    return frozenset((cpuinfo_field("flags", path) or "").split())


def cpu_model(path: str = "/proc/cpuinfo") -> str:
    """The CPU's model name (Linux's ``model name``; elsewhere ``platform``'s processor or
    machine)."""
    return cpuinfo_field("model name", path) or platform.processor() or platform.machine()


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the OS has one), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _numpy_dispatch_names(version: str | None) -> tuple[str, ...]:
    """numpy's AVX-512 targets under the names its ``version`` knows (the newer names when
    the version cannot be read)."""
    try:
        major, minor = (int(p) for p in (version or "").split(".")[:2])
    except ValueError:
        return NUMPY_AVX512_TARGETS["new"]
    return NUMPY_AVX512_TARGETS["new" if (major, minor) >= (2, 4) else "old"]


def reproducible_defaults(*, machine: str | None = None, flags=None,
                          numpy_version: str | None = None) -> dict[str, str]:
    """The variables (name -> value) that make a process's numbers the same on every
    machine of its kind: one BLAS thread everywhere; on x86-64 with AVX2 and FMA, OpenBLAS's
    Haswell kernels and numpy's AVX-512 loops off. ``machine``, ``flags`` and
    ``numpy_version`` default to this machine's (for tests)."""
    out = {var: "1" for var in SINGLE_THREAD_VARS}
    machine = (platform.machine() if machine is None else machine).lower()
    flags = cpu_flags() if flags is None else frozenset(flags)
    if machine in ("x86_64", "amd64") and {"avx2", "fma"} <= flags:
        out["OPENBLAS_CORETYPE"] = "Haswell"
        if numpy_version is None:
            try:
                from importlib.metadata import version

                numpy_version = version("numpy")
            except Exception:  # noqa: BLE001 - no metadata: the newer names
                numpy_version = None
        out["NPY_DISABLE_CPU_FEATURES"] = " ".join(_numpy_dispatch_names(numpy_version))
    return out


def apply(environ=None) -> dict[str, str]:
    """Set :func:`reproducible_defaults` in ``environ`` (default ``os.environ``) where it
    does not set them already; returns what it set. Call it before numpy is imported (a
    later call changes nothing in this process, only in the processes it starts)."""
    environ = os.environ if environ is None else environ
    done = {}
    for var, val in reproducible_defaults().items():
        if var not in environ:
            environ[var] = val
            done[var] = val
    return done

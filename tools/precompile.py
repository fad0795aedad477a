"""Compile the project's numba kernels ahead of their first use, into numba's on-disk cache.

Every compiled kernel of the project lives in a module named ``_*_numba.py`` of ``reglib`` or
``testbed`` and is declared ``njit(cache=True)``: numba compiles it at its first call with a
new argument-type signature and keeps the machine code in ``__pycache__`` beside the source,
so that later processes load it in milliseconds. The first ``testbed run`` on a fresh
checkout would otherwise spend about 40 s of CPU compiling (measured on a 2-core EPYC VM).

This tool compiles, from a manifest of signatures (``numba_signatures.txt`` beside it), the
very signatures a ``testbed run`` calls, so that the run finds them all in the cache. The
editable install runs it (``tools/build_backend.py``), and a developer may run it by hand:

    python tools/precompile.py                 # compile the manifest's signatures (2 processes)
    python tools/precompile.py --record SCENE… # run those scenes' main job, add what it compiled

It needs numpy, scipy and numba only (the kernel modules import nothing else), so it also runs
in pip's isolated build environment. The cache is valid for the numba version and CPU that
wrote it; any other, or an edited source file, makes numba compile again at first use (it
checks the source's time stamp and size, and its own version), so a stale cache costs time,
never correctness.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import importlib
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MANIFEST = Path(__file__).resolve().parent / "numba_signatures.txt"
PACKAGES = ("reglib", "testbed")


def kernel_modules(root: Path = ROOT) -> list[str]:
    """Dotted names of the modules that hold compiled kernels (``<package>/_*_numba.py``)."""
    return sorted(f"{pkg}.{p.stem}" for pkg in PACKAGES for p in (root / pkg).glob("_*_numba.py"))


def dispatchers(module_name: str) -> dict[str, object]:
    """The module's numba dispatchers by attribute name (one name each, the first sorted)."""
    from numba.core.dispatcher import Dispatcher

    module = importlib.import_module(module_name)
    found: dict[int, tuple[str, object]] = {}
    for name in sorted(vars(module)):
        obj = getattr(module, name)
        if isinstance(obj, Dispatcher) and id(obj) not in found:
            found[id(obj)] = (name, obj)
    return dict(found.values())


def signature_text(signature: tuple) -> str:
    """A signature as text that :func:`parse_signature` reads back (numba types' reprs)."""
    return "(" + ", ".join(repr(t) for t in signature) + ("," if len(signature) == 1 else "") + ")"


def parse_signature(text: str) -> tuple:
    """Read a signature written by :func:`signature_text` into a tuple of numba types."""
    from numba.core import types

    namespace = {name: getattr(types, name) for name in dir(types) if not name.startswith("_")}
    # types whose repr is their class's name: the instance numba makes for such a value
    namespace["NumPyRandomGeneratorType"] = _generator_type()
    value = eval(text, {"__builtins__": {}}, namespace)  # noqa: S307 - our own manifest
    if not isinstance(value, tuple) or not all(isinstance(t, types.Type) for t in value):
        raise ValueError(f"not a tuple of numba types: {text!r}")
    return value


def _generator_type():
    import numba
    import numpy as np

    return numba.typeof(np.random.default_rng(0))


def read_manifest(path: Path = MANIFEST) -> dict[str, dict[str, list[str]]]:
    """``{module: {function: [signature text, ...]}}`` from the manifest's lines.

    A line is ``module:function (type, type, ...)``; blank lines and ``#`` comments are
    skipped. A malformed line raises ValueError naming the file and line number.
    """
    out: dict[str, dict[str, list[str]]] = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        head, sep, sig = line.partition(" ")
        module, colon, function = head.partition(":")
        if not (sep and colon and module and function and sig.startswith("(")):
            raise ValueError(
                f"{path}:{number}: expected 'module:function (types...)', got {line!r}")
        out.setdefault(module, {}).setdefault(function, []).append(sig)
    return out


def write_manifest(entries: dict[str, dict[str, list[str]]], path: Path = MANIFEST) -> None:
    lines = [
        "# Signatures compiled ahead of the first run by tools/precompile.py (made by",
        "# `python tools/precompile.py --record SCENE...`; one line per module:function and",
        "# argument-type signature, in numba's own type reprs).",
    ]
    for module in sorted(entries):
        for function in sorted(entries[module]):
            sigs = sorted(set(entries[module][function]))
            lines += [f"{module}:{function} {sig}" for sig in sigs]
    path.write_text("\n".join(lines) + "\n")


def compile_module(module_name: str, signatures: dict[str, list[str]]
                   ) -> tuple[int, int, list[str], float]:
    """Compile (or load from the cache) each listed signature of one module.

    Returns (loaded from the cache, compiled, failures as one line each, CPU seconds); a
    signature that cannot be read or compiled is a failure, not an exception, so that one
    stale line costs only its own kernel's first-use compilation.
    """
    start = time.process_time()
    loaded = compiled = 0
    failures: list[str] = []
    try:
        found = dispatchers(module_name)
    except Exception as exc:  # noqa: BLE001 - reported, the others still compiled
        return 0, 0, [f"{module_name}: cannot import ({type(exc).__name__}: {exc})"], 0.0
    for function, sigs in signatures.items():
        if function not in found:
            failures.append(f"{module_name}: no compiled kernel {function!r}")
            continue
        disp = found[function]
        for text in sigs:
            try:
                sig = parse_signature(text)
                hits = sum(disp.stats.cache_hits.values())
                disp.compile(sig)
            except Exception as exc:  # noqa: BLE001 - reported
                failures.append(f"{module_name}:{function} {text}: {type(exc).__name__}: {exc}")
                continue
            if sum(disp.stats.cache_hits.values()) > hits:
                loaded += 1
            else:
                compiled += 1
    return loaded, compiled, failures, time.process_time() - start


def _compile_job(args: tuple[str, dict[str, list[str]], str]
                 ) -> tuple[int, int, list[str], float]:
    module_name, signatures, root = args
    if root not in sys.path:
        sys.path.insert(0, root)
    return compile_module(module_name, signatures)


def precompile(workers: int = 2, manifest: Path = MANIFEST, verbose: bool = True) -> dict:
    """Compile every signature of the manifest, modules spread over ``workers`` processes.

    Returns ``{"modules", "loaded", "compiled", "failures", "cpu_s", "wall_s"}``.
    """
    entries = read_manifest(manifest)
    start = time.perf_counter()
    jobs = [(m, entries[m], str(ROOT)) for m in sorted(entries)]
    # the largest modules first, so that two workers end together
    jobs.sort(key=lambda job: -sum(len(s) for s in job[1].values()))
    totals = {"modules": len(jobs), "loaded": 0, "compiled": 0, "failures": [], "cpu_s": 0.0}
    if workers <= 1:
        results = map(_compile_job, jobs)
    else:
        pool = concurrent.futures.ProcessPoolExecutor(max_workers=workers)
        results = pool.map(_compile_job, jobs)
    for (module_name, _, _), (loaded, compiled, failures, cpu) in zip(jobs, results):
        totals["loaded"] += loaded
        totals["compiled"] += compiled
        totals["failures"] += failures
        totals["cpu_s"] += cpu
        if verbose:
            print(f"  {module_name}: {compiled} compiled, {loaded} from the cache "
                  f"({cpu:.1f} s CPU)", file=sys.stderr)
    if workers > 1:
        pool.shutdown()
    totals["wall_s"] = time.perf_counter() - start
    return totals


def record(scenes: list[str], manifest: Path = MANIFEST) -> dict[str, dict[str, list[str]]]:
    """Run each scene's main job in this process; add every signature compiled to the manifest."""
    sys.path.insert(0, str(ROOT))
    from studies.cli import main

    for scene in scenes:
        code = main(["run", scene, "--json"])
        if code not in (0, None):
            raise SystemExit(f"testbed run {scene} exited {code}")
    entries = read_manifest(manifest) if manifest.exists() else {}
    for module_name in kernel_modules():
        for function, disp in dispatchers(module_name).items():
            for sig in disp.signatures:
                entries.setdefault(module_name, {}).setdefault(function, []).append(
                    signature_text(sig))
    write_manifest(entries, manifest)
    return entries


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--record", nargs="+", metavar="SCENE",
                        help="run these scenes' main job and add the signatures they compiled")
    parser.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    args = parser.parse_args(argv)
    if args.record:
        entries = record(args.record)
        n = sum(len(set(s)) for fs in entries.values() for s in fs.values())
        print(f"{MANIFEST}: {n} signatures", file=sys.stderr)
        return 0
    sys.path.insert(0, str(ROOT))
    totals = precompile(workers=max(1, args.workers))
    print(f"precompiled {totals['compiled']} kernel signatures ({totals['loaded']} already cached) "
          f"in {totals['wall_s']:.1f} s ({totals['cpu_s']:.1f} s CPU)", file=sys.stderr)
    for line in totals["failures"]:
        print(f"  not precompiled: {line}", file=sys.stderr)
    return 1 if totals["failures"] else 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())

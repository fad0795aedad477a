"""The kernels' ahead-of-run compilation (tools/precompile.py, run by the editable install)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools"))

import precompile  # noqa: E402


def test_every_manifest_line_names_a_kernel_and_reads_back():
    entries = precompile.read_manifest()
    modules = precompile.kernel_modules()
    assert set(entries) <= set(modules)
    n = 0
    for module, functions in entries.items():
        found = precompile.dispatchers(module)
        for function, sigs in functions.items():
            assert function in found, f"{module}:{function} is not a compiled kernel"
            for text in sigs:
                sig = precompile.parse_signature(text)
                assert precompile.signature_text(sig) == text
                n += 1
    # the main job's kernels: imaging, markers, CT, surfaces, contours, closest points, pose
    assert n >= 30
    assert {"testbed._fan_numba", "reglib._pose_numba", "reglib._closest_numba"} <= set(entries)


def test_signature_text_round_trips_the_types_numba_sees():
    import numba

    values = (np.zeros((3, 2)), np.zeros(4, np.int32)[::2], np.zeros((2, 2), np.uint8).T,
              1.5, 3, True, np.random.default_rng(0), (1.0, 2.0))
    sig = tuple(numba.typeof(v) for v in values)
    readonly = np.zeros(3)
    readonly.setflags(write=False)
    sig += (numba.typeof(readonly),)
    assert precompile.parse_signature(precompile.signature_text(sig)) == sig
    one = (numba.typeof(np.zeros(2)),)
    assert precompile.parse_signature(precompile.signature_text(one)) == one


def test_a_malformed_manifest_line_is_named(tmp_path):
    path = tmp_path / "m.txt"
    path.write_text("# comment\nreglib._pose_numba:irls (float64,)\nreglib._pose_numba irls\n")
    with pytest.raises(ValueError, match=r"m\.txt:3"):
        precompile.read_manifest(path)


def test_a_stale_line_is_a_failure_not_an_exception():
    loaded, compiled, failures, _ = precompile.compile_module(
        "reglib._pose_numba", {"no_such_kernel": ["(float64,)"],
                               "perp_basis": ["(NoSuchType,)"]})
    assert (loaded, compiled) == (0, 0)
    assert len(failures) == 2
    assert "no_such_kernel" in failures[0] and "NoSuchType" in failures[1]


@pytest.mark.slow
def test_after_precompiling_the_main_job_compiles_nothing(tmp_path):
    """A fresh numba cache, the manifest compiled into it, then `testbed run` on the default
    scene: numba saves no new cache index, i.e. the run compiled no kernel (~35 s)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1")
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "precompile.py")], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "precompiled" in done.stderr
    env["NUMBA_DEBUG_CACHE"] = "1"
    run = subprocess.run([sys.executable, "-m", "studies.cli", "run", "--json"], env=env,
                         capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-2000:]
    out = run.stdout
    assert "index loaded" in out
    saved = [line for line in out.splitlines() if "index saved" in line]
    assert not saved, "compiled at the run (add to the manifest with --record):\n" + "\n".join(
        saved)


def test_an_sdist_carries_the_build_backend(tmp_path):
    """pyproject.toml names tools/build_backend.py as the backend: an sdist without it could
    not be built into a wheel (MANIFEST.in includes the folder)."""
    import tarfile

    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"],
                           cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    src = tmp_path / "src"
    for f in files:
        if (ROOT / f).is_file():
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            (src / f).write_bytes((ROOT / f).read_bytes())
    done = subprocess.run([sys.executable, "-c", "from setuptools import build_meta; "
                           "print(build_meta.build_sdist('dist'))"], cwd=src,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    name = done.stdout.strip().splitlines()[-1]
    with tarfile.open(src / "dist" / name) as tar:
        members = {m.split("/", 1)[1] for m in tar.getnames() if "/" in m}
    assert {"tools/build_backend.py", "tools/precompile.py", "tools/numba_signatures.txt",
            "pyproject.toml"} <= members


def test_the_editable_build_writes_the_packages_bytecode(tmp_path):
    """tools/build_backend._bytecode compiles every module of the packages to the .pyc that
    the interpreter then imports, even where PYTHONDONTWRITEBYTECODE keeps Python itself from
    writing them."""
    import importlib.util

    import build_backend

    mods = []
    for pkg in build_backend.PACKAGES:
        (tmp_path / pkg / "sub").mkdir(parents=True)
        for rel in ("__init__.py", "a.py", "sub/__init__.py", "sub/b.py"):
            (tmp_path / pkg / rel).write_text(f"VALUE = {len(mods)}\n")
            mods.append(tmp_path / pkg / rel)
    build_backend._bytecode(tmp_path)
    for m in mods:
        assert Path(importlib.util.cache_from_source(str(m))).is_file(), m
    # and the interpreter takes them: no module of the packages compiled from source
    out = subprocess.run(
        [sys.executable, "-v", "-c", "; ".join(f"import {p}.sub.b, {p}.a"
                                                 for p in build_backend.PACKAGES)],
        cwd=tmp_path, env=dict(os.environ, PYTHONDONTWRITEBYTECODE="1"),
        capture_output=True, text=True, check=True).stderr
    loaded = [ln for ln in out.splitlines() if ln.startswith("# code object from")
              and str(tmp_path) in ln]
    assert len(loaded) == len(mods) and all(".pyc" in ln for ln in loaded), loaded

"""The project's build backend: setuptools', and at an editable install the numba kernels
compiled into their on-disk cache (``tools/precompile.py``).

``pip install -e .`` builds through this module (``[build-system]`` of pyproject.toml), so
that the first ``testbed run`` of a fresh checkout finds its compiled kernels in
``__pycache__`` instead of spending about 40 s of CPU compiling them. The editable build asks
for numpy, scipy and numba in pip's build environment, the kernels' only imports. Other builds
(``pip install .``, wheels, sdists) are setuptools' own: there the code is copied into
site-packages and numba compiles and caches it there at first use. An sdist carries this
folder (MANIFEST.in), since its pyproject.toml names this backend.

It also compiles the packages' modules to bytecode (:func:`_bytecode`).

``TESTBED_PRECOMPILE=0`` skips both. It never fails an install: a kernel it could not
compile is compiled at its first use, as without it, and a line on stderr says which.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F403 - the backend's other hooks unchanged

KERNEL_REQUIRES = ["numpy>=1.26", "scipy>=1.11", "numba>=0.60"]
PRECOMPILE = Path(__file__).resolve().parent / "precompile.py"


def _wanted() -> bool:
    return os.environ.get("TESTBED_PRECOMPILE", "1") != "0"


def get_requires_for_build_editable(config_settings=None):
    extra = KERNEL_REQUIRES if _wanted() else []
    return _setuptools.get_requires_for_build_editable(config_settings) + extra


def build_editable(wheel_directory, config_settings=None, metadata_directory=None):
    name = _setuptools.build_editable(wheel_directory, config_settings, metadata_directory)
    if _wanted():
        _precompile()
        _bytecode()
    return name


#: the packages whose bytecode an editable install writes
PACKAGES = ("reglib", "testbed", "studies", "scenes")


def _bytecode(root: Path | None = None) -> None:
    """Compile the packages' modules to ``__pycache__/*.pyc``, as pip does for the code it
    copies into site-packages but not for an editable install's source tree: where
    ``PYTHONDONTWRITEBYTECODE`` is set, Python never writes them itself and compiled the
    52 modules of a ``testbed run`` from source every time (0.15 s of its CPU). An edited
    module's stale .pyc is recompiled in memory, never used. ``root``: the project's folder
    (default: this file's parent's)."""
    import compileall

    root = Path(__file__).resolve().parent.parent if root is None else Path(root)
    for pkg in PACKAGES:
        try:        # like the precompile, it never fails an install
            done = compileall.compile_dir(str(root / pkg), quiet=1)
        except Exception as exc:  # noqa: BLE001
            done, why = False, f" ({exc})"
        else:
            why = ""
        if not done:
            print(f"warning: some modules of {pkg} were not compiled to bytecode{why}; "
                  "Python compiles them at import", file=sys.stderr)


def _precompile() -> None:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    try:
        done = subprocess.run([sys.executable, str(PRECOMPILE)], env=env, timeout=1200,
                              capture_output=True, text=True)
    except (OSError, subprocess.SubprocessError) as exc:
        print(f"warning: numba kernels not precompiled ({exc}); they compile at first use",
              file=sys.stderr)
        return
    sys.stderr.write(done.stderr)
    if done.returncode != 0:
        print("warning: some numba kernels were not precompiled (above); they compile at "
              "first use", file=sys.stderr)

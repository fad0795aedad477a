"""pytest set-up shared by every test.

The numeric environment the ``testbed`` command runs with (``studies.numerics``: one BLAS
thread per process, and the AVX2 code on an x86 CPU that has AVX-512), unless the user set
the variables: they must be set before numpy is first imported, which this file is, ahead
of every test module. A multi-threaded BLAS sums in another order (the default run's mTRE
moves in the third decimal) and, on a shared 2-core machine, made the snakes' small matrix
inversions 40x slower; AVX-512 kernels round otherwise and moved it in the second. ``python
-m pytest`` (the README's command) and ``.ci/run`` then run alike.

Also: the procedural phantoms' disk cache in a folder of the session (below), and the
number of pytest-xdist workers that ``-n auto`` (pyproject's addopts) starts, and the slow
tests run first.
"""

import atexit
import os
import shutil
import tempfile

from studies import numerics

numerics.apply()

# the procedural phantoms' disk cache (testbed.phantom._csg_meshes) in a folder of this
# session, inherited by the commands the tests start: every session builds its femurs
# anew, and the fifty of test_phantom.py do not push a user's cached ones out
if "TESTBED_CACHE_DIR" not in os.environ:
    os.environ["TESTBED_CACHE_DIR"] = tempfile.mkdtemp(prefix="testbed-cache-")
    atexit.register(shutil.rmtree, os.environ["TESTBED_CACHE_DIR"], ignore_errors=True)


#: the most workers ``-n auto`` starts: each one imports numba, pybullet and trimesh (about
#: 0.5 GB), and some tests start two worker processes of their own
MAX_TEST_WORKERS = 4


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker per core this process may run on, at most
    :data:`MAX_TEST_WORKERS`. On a 2-core machine (a Xeon at 2.1 GHz, 2026-11-27) the suite
    took 751 s on one core and 414 s on two workers with work stealing (494 s with whole
    files per worker: the kernels' precompile test alone takes 175 s)."""
    return min(numerics.usable_cores(), MAX_TEST_WORKERS)


def pytest_collection_modifyitems(config, items):
    """The tests marked ``slow`` first (otherwise in their usual order): on workers, a long
    test near the end of the collection (tests/testbed/test_generate.py's, 100 s) ran alone
    after the other worker had finished. Started first, the long ones overlap the short."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)

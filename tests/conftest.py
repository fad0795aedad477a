"""pytest set-up shared by every test.

The numeric environment the ``testbed`` command runs with (``studies.numerics``: one BLAS
thread per process, and the AVX2 code on an x86 CPU that has AVX-512), unless the user set
the variables: they must be set before numpy is first imported, which this file is, ahead
of every test module. A multi-threaded BLAS sums in another order (the default run's mTRE
moves in the third decimal) and, on a shared 2-core machine, made the snakes' small matrix
inversions 40x slower; AVX-512 kernels round otherwise and moved it in the second. ``python
-m pytest`` (the README's command) and ``.ci/run`` then run alike.

Also: the procedural phantoms' disk cache in a folder of the session (below).
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

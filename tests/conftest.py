"""pytest set-up shared by every test.

One BLAS thread per process, as the ``testbed`` command runs (``studies.cli``), unless the
user set the variables: they must be set before numpy is first imported, which this file
is, ahead of every test module. A multi-threaded BLAS sums in another order (the default
run's mTRE moves in the third decimal) and, on a shared 2-core machine, made the snakes'
small matrix inversions 40x slower. ``python -m pytest`` (the README's command) and
``.ci/run`` then run alike.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

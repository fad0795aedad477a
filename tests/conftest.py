"""pytest set-up shared by every test.

The numeric environment the ``testbed`` command runs with (``studies.numerics``: one BLAS
thread per process, and the AVX2 code on an x86 CPU that has AVX-512), unless the user set
the variables: they must be set before numpy is first imported, which this file is, ahead
of every test module. A multi-threaded BLAS sums in another order (the default run's mTRE
moves in the third decimal) and, on a shared 2-core machine, made the snakes' small matrix
inversions 40x slower; AVX-512 kernels round otherwise and moved it in the second. ``python
-m pytest`` (the README's command) and ``.ci/run`` then run alike.
"""

from studies import numerics

numerics.apply()

"""Imported first by the process pool's fork server (``studies.runner._run_pool``), before
the modules it preloads: a Ctrl-C of the study prints no traceback from there.

A terminal's Ctrl-C reaches every process of the study's group, and two tracebacks
followed the study's own "interrupted" when it came in the first seconds of a study (a
review; 4 of 12 interrupts between 1.0 and 2.1 s on view-setups --workers 2):

- The standard library's fork server ignores Ctrl-C only once its preloads are imported;
  during them (pandas, numpy, trimesh) it printed the import's KeyboardInterrupt. It
  ignores it from here on. The workers get Python's default handler back
  (``studies.runner._worker_start``).
- A worker the server was still starting when the study's process ended found the pool's
  semaphores already removed and printed ``SemLock._rebuild``'s FileNotFoundError. That
  error, there, only means that the study that asked for the worker is gone: it is left
  unsaid (every other error of a starting worker is printed as before).
"""

import signal
import sys

signal.signal(signal.SIGINT, signal.SIG_IGN)

_print_exception = sys.excepthook


def _quiet_when_the_pool_is_gone(exc_type, exc, tb) -> None:
    last = tb
    while last is not None and last.tb_next is not None:
        last = last.tb_next
    where = last.tb_frame.f_code if last is not None else None
    if (exc_type is FileNotFoundError and where is not None
            and where.co_filename.endswith("synchronize.py")
            and where.co_name == "__setstate__"):
        return
    _print_exception(exc_type, exc, tb)


sys.excepthook = _quiet_when_the_pool_is_gone

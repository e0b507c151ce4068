"""BLAS threads for processes that share a machine: one each, unless the user chose otherwise."""

from __future__ import annotations

import os

#: Thread counts of the BLAS/OpenMP libraries numpy and scipy may load. A daemon's linear algebra is
#: small (e.g. a 270×270 eigh) and shares the machine with the others: a thread per core then mostly
#: waits on the other daemons and is many times slower than one thread, so the daemons run it
#: single-threaded.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded_blas(environ=os.environ) -> None:
    """Make BLAS single-threaded unless the user chose otherwise (a variable already set wins).

    Call before numpy is first imported: the libraries read these variables once, when loaded."""
    for name in BLAS_THREAD_VARIABLES:
        environ.setdefault(name, "1")

"""How many BLAS threads the numerical runs use.

The problems are small and dense-ish (a few hundred unknowns): on a busy two-core machine one
BLAS thread is faster than several competing for the cores (a flexure curve took 1-7 s with one
thread against up to 18 s with the default).  ``QPSCALE_BLAS_THREADS`` overrides the default of
one.  It implements no formulation.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

DEFAULT_BLAS_THREADS = 1


def blas_threads() -> int:
    """Threads asked for by ``QPSCALE_BLAS_THREADS`` (a positive integer), else 1."""
    raw = os.environ.get("QPSCALE_BLAS_THREADS", "")
    try:
        value = int(raw)
    except ValueError:
        return DEFAULT_BLAS_THREADS
    return value if value > 0 else DEFAULT_BLAS_THREADS


@contextmanager
def limited_blas() -> Iterator[None]:
    """Run the body with :func:`blas_threads` BLAS/OpenMP threads (threadpoolctl)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=blas_threads()):
        yield

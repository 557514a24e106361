"""One BLAS thread for the small, tall least-squares problems of identification and diagnosis.

The diagnosis solves thousands of least-squares problems of a few columns over
some ten thousand samples (screening regressions, QR and SVD, Jacobian
products). Split over OpenBLAS's threads, each such call costs more in
hand-over than it gains, and on a machine busy with other work the threads
spin waiting for one another: ``diagnose`` on the EMPS log used 6.0 s of CPU
with the default threads and 2.9 s with one (same result). A bench that
diagnoses several axes at once runs one process per axis (the fleet) instead.

:func:`one_blas_thread` limits the BLAS libraries loaded in this process to one
thread for the duration of a ``with`` block (``threadpoolctl``) and restores
them after it; the user's own settings outside it are untouched. It limits the
libraries loaded when it starts, so numpy's and scipy's (two OpenBLAS builds)
are both imported first.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy  # noqa: F401  (numpy's and scipy's BLAS are two libraries: both loaded, then limited)
import scipy.linalg  # noqa: F401
from threadpoolctl import threadpool_limits


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS and LAPACK calls inside the block use one thread; restored on exit."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield

"""One BLAS thread for the small, tall least-squares problems of identification and diagnosis.

Identification and diagnosis solve thousands of least-squares problems of a few
columns over some ten thousand samples (pair regressions in the delay scan,
screening regressions, QR and SVD, Jacobian products). Split over OpenBLAS's
threads, each such call costs more in hand-over than it gains, and on a machine
busy with other work the threads spin waiting for one another:

- ``diagnose`` on the EMPS log used 6.0 s of CPU with the default threads and
  2.9 s with one (same result);
- identifying a default ``sidbe`` log of ``sim://`` (32 000 samples) took 0.23 s
  on a quiet 2-core machine and 2.9 s beside two busy processes with the
  default threads, 0.21 s and 0.32 s with one (same model).

A bench that identifies several axes at once runs one process per axis (the
fleet) instead. The command line goes further: its processes load OpenBLAS with
one thread (``OPENBLAS_NUM_THREADS=1`` unless the environment sets it,
:data:`servobench.bench.cli.BLAS_THREADS`), as the threads numpy's and scipy's
builds start when they load cost a process 0.15-0.2 s of CPU.

:func:`one_blas_thread` limits the BLAS libraries loaded in this process to one
thread for the duration of a ``with`` block (``threadpoolctl``) and restores
them when the thread's outermost such block exits (blocks nest: an inner one
changes nothing, and its exit restores nothing); the user's own settings
outside the blocks are untouched.
:func:`on_one_blas_thread` is the same as a decorator, on the entry points of
identification, validation, ``sidbe`` and commissioning. It limits the
libraries loaded when the block starts, so numpy's and scipy's (two OpenBLAS
builds) are both imported first.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import numpy  # noqa: F401  (numpy's and scipy's BLAS are two libraries: both loaded, then limited)
import scipy.linalg  # noqa: F401
from threadpoolctl import threadpool_limits

F = TypeVar("F", bound=Callable[..., Any])

_local = threading.local()  # this thread's depth of blocks and the limits its outermost one set


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS and LAPACK calls inside the block use one thread; restored when this thread's
    outermost block exits."""
    depth = getattr(_local, "depth", 0)
    if depth == 0:
        _local.limits = threadpool_limits(limits=1, user_api="blas")
    _local.depth = depth + 1
    try:
        yield
    finally:
        _local.depth = depth
        if depth == 0:
            _local.limits.restore_original_limits()
            _local.limits = None


def on_one_blas_thread(fn: F) -> F:
    """``fn`` run inside :func:`one_blas_thread`."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with one_blas_thread():
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]

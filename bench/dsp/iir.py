"""Infinite-impulse-response filters: the Butterworth low-pass, direct form II transposed.

The same numbers as :func:`scipy.signal.butter`, :func:`scipy.signal.lfilter` and
:func:`scipy.signal.lfilter_zi` (bit for bit on the filters the package designs:
``tests/test_dsp.py``), and ``filtfilt``'s two passes in one call
(:func:`filtfilt_padded`, ``tests/test_lowpass.py``), without importing :mod:`scipy.signal`.
The filter's loop is compiled with numba (``cache=True``), one column at a time, in scipy's
order of operations.
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit


@functools.lru_cache(maxsize=64)
def butter_lowpass(order: int, wn: float) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.signal.butter(order, wn)``: a digital Butterworth low-pass, transfer function ``(b, a)``.

    ``wn``: the cut-off as a fraction of the Nyquist frequency, ``0 < wn < 1``. The analog
    prototype's poles, pre-warped and taken through the bilinear transform as scipy does; the
    arrays are read-only and cached per ``(order, wn)``.
    """
    if order < 1:
        raise ValueError(f"filter order must be at least 1, got {order}")
    if not 0.0 < wn < 1.0:
        raise ValueError(f"digital filter cut-off must lie in (0, 1) of Nyquist, got {wn}")
    m = np.arange(-order + 1, order, 2, dtype=np.float64)
    p = -np.exp(1j * np.pi * m / (2 * order))  # scipy.signal.buttap: no zeros, gain 1
    fs = 2.0
    warped = float(2 * fs * np.tan(np.pi * np.asarray(wn, dtype=np.float64) / fs))  # numpy's tan
    z = np.array([])
    p = warped * p  # lp2lp_zpk
    k = 1.0 * warped ** (len(p) - len(z))
    fs2 = 2.0 * fs  # bilinear_zpk
    z_z = np.append((fs2 + z) / (fs2 - z), -np.ones(len(p) - len(z)))
    p_z = (fs2 + p) / (fs2 - p)
    k_z = k * np.real(np.prod(fs2 - z) / np.prod(fs2 - p))
    b = k_z * _poly(z_z)  # zpk2tf
    a = _poly(p_z)
    b.flags.writeable = False
    a.flags.writeable = False
    return b, a


def _poly(roots: np.ndarray) -> np.ndarray:
    """The monic polynomial of ``roots``, real where they come in conjugate pairs (scipy's
    ``_polyutils.poly``: it compares the sorted imaginary parts, where :func:`numpy.poly` sorts
    the roots themselves and may keep a complex result)."""
    a = np.ones((1,), dtype=roots.dtype)
    for root in roots:
        a = np.convolve(a, np.array([np.ones_like(root), -root]), mode="full")
    if np.iscomplexobj(a) and np.all(np.sort(roots.imag) == np.sort(np.conj(roots).imag)):
        a = np.array(a.real, copy=True)
    return a


def _normalised(b: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``b`` and ``a`` as float arrays of one length (zeros appended), leading zeros of ``a`` dropped."""
    b = np.atleast_1d(np.asarray(b, dtype=float))
    a = np.atleast_1d(np.asarray(a, dtype=float))
    while a.size > 1 and a[0] == 0.0:
        a = a[1:]
    if a.size < 1 or a[0] == 0.0:
        raise ValueError("the filter needs a nonzero leading denominator coefficient")
    n = max(a.size, b.size)
    b = np.concatenate((b, np.zeros(n - b.size)))
    a = np.concatenate((a, np.zeros(n - a.size)))
    return b, a


def _monic(b: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_normalised`, both divided by ``a[0]`` (exact where it is 1, as scipy skips it)."""
    b, a = _normalised(b, a)
    return b / a[0], a / a[0]


def lfilter_zi(b: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``scipy.signal.lfilter_zi(b, a)``: the state of the filter in its step response's steady
    state, shape ``(max(len(a), len(b)) - 1,)``."""
    b, a = _monic(b, a)
    n = a.size
    companion = np.zeros((n - 1, n - 1))  # scipy.linalg.companion(a)
    companion[0] = -a[1:] / (1.0 * a[0])
    companion[np.arange(1, n - 1), np.arange(n - 2)] = 1.0
    i_minus_a = np.eye(n - 1) - companion.T
    return np.linalg.solve(i_minus_a, b[1:] - a[1:] * b[0])


@njit(cache=True, inline="always")
def _step(b, a, z, xn):  # pragma: no cover - compiled
    """One sample ``xn`` through the filter in direct form II transposed, its state ``z``
    (``len(b) - 1``, updated in place); the output. ``b`` and ``a`` normalised, equal lengths.
    scipy's loop (``_lfilter.c``), operation for operation."""
    order = b.size - 1
    if order == 0:
        return xn * b[0]
    yn = z[0] + b[0] * xn
    for i in range(order - 1):
        z[i] = z[i + 1] + xn * b[i + 1] - yn * a[i + 1]
    z[order - 1] = xn * b[order] - yn * a[order]
    return yn


@njit(cache=True)
def _filter_columns(b, a, x, z):  # pragma: no cover - compiled
    """:func:`_step` over the rows of ``x`` (n, m), each column from its state ``z`` (order, m),
    which ends as the final state."""
    n, m = x.shape
    y = np.empty_like(x)
    state = np.empty(z.shape[0])
    for j in range(m):
        state[:] = z[:, j]
        for k in range(n):
            y[k, j] = _step(b, a, state, x[k, j])
        z[:, j] = state
    return y


@njit(cache=True)
def _filtfilt_columns(b, a, zi, ext, pad):  # pragma: no cover - compiled
    """:func:`_step` forward over each column of ``ext`` (rows, m) from ``zi`` times its first
    sample, then backward over that output from ``zi`` times its last; the backward pass's output
    in forward order without ``pad`` rows at each end: ``filtfilt``'s two passes in one call."""
    rows, m = ext.shape
    out = np.empty((rows - 2 * pad, m))
    fwd = np.empty(rows)
    z = np.empty(zi.size)
    for j in range(m):
        for i in range(zi.size):
            z[i] = zi[i] * ext[0, j]
        for k in range(rows):
            fwd[k] = _step(b, a, z, ext[k, j])
        for i in range(zi.size):
            z[i] = zi[i] * fwd[rows - 1]
        for k in range(rows - 1, -1, -1):
            yn = _step(b, a, z, fwd[k])
            if pad <= k < rows - pad:
                out[k - pad, j] = yn
    return out


def filtfilt_padded(b: np.ndarray, a: np.ndarray, zi: np.ndarray, ext: np.ndarray, pad: int) -> np.ndarray:
    """The two passes of ``scipy.signal.filtfilt`` over ``ext`` (rows, m), the signal already
    extended by ``pad`` rows at each end, from the steady state ``zi``
    (:func:`lfilter_zi`); the filtered signal without the extension, shape ``(rows - 2 pad, m)``.
    Equal, bit for bit, to two :func:`lfilter` calls with ``zi`` scaled by the first and the
    last sample, in one compiled call (the diagnosis filters tens of thousands of commands)."""
    b, a = _monic(b, a)
    if b.size < 2:
        raise ValueError("filtfilt_padded needs a filter of order 1 or more")
    ext = np.ascontiguousarray(ext, dtype=float)
    return _filtfilt_columns(b, a, np.ascontiguousarray(zi, dtype=float), ext, int(pad))


def lfilter(
    b: np.ndarray, a: np.ndarray, x: np.ndarray, axis: int = -1, zi: np.ndarray | None = None
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """``scipy.signal.lfilter(b, a, x, axis, zi)`` for real float arrays.

    Returns the filtered ``x``; with ``zi`` (the initial state, shape ``x``'s with ``axis``
    of length ``max(len(a), len(b)) - 1``) also the final state, as scipy does.
    """
    b, a = _monic(b, a)
    x = np.asarray(x, dtype=float)
    moved = np.moveaxis(x, axis, 0)
    rows = moved.shape[0]
    columns = np.ascontiguousarray(moved.reshape(rows, -1))
    order = b.size - 1
    if zi is None:
        state = np.zeros((order, columns.shape[1]))
    else:
        zi = np.asarray(zi, dtype=float)
        want = (order,) + moved.shape[1:]
        state = np.moveaxis(zi, axis, 0) if zi.ndim == x.ndim else zi
        if state.shape != want:
            raise ValueError(
                f"initial state of shape {zi.shape} does not fit the signal {x.shape} along axis {axis}"
            )
        state = np.array(state.reshape(order, -1), dtype=float, order="C")
    y = _filter_columns(b, a, columns, state).reshape(moved.shape)
    y = np.moveaxis(y, 0, axis)
    if zi is None:
        return y
    return y, np.moveaxis(state.reshape((order,) + moved.shape[1:]), 0, axis)


def freqz(b: np.ndarray, a: np.ndarray, points: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.signal.freqz(b, a, worN=points)``: angular frequencies ``w`` [rad/sample] from 0
    up to (not including) pi, and the response ``h`` there (both polynomials in ``e^-jw`` by
    Horner's rule, as scipy evaluates a recursive filter's)."""
    b, a = _normalised(b, a)
    w = np.linspace(0.0, np.pi, points, endpoint=False)
    zm1 = np.exp(-1j * w)
    return w, _horner(b, zm1) / _horner(a, zm1)


def _horner(c: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``numpy.polynomial.polynomial.polyval(x, c)``: ``c[0] + c[1] x + ...``."""
    out = c[-1] + x * 0
    for coef in c[-2::-1]:
        out = coef + out * x
    return out

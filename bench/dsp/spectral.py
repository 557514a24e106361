"""Welch's spectral densities: averaged periodograms of overlapping Hann-windowed segments.

:func:`scipy.signal.welch` and :func:`scipy.signal.csd` at the arguments the package uses (a
periodic Hann window, half-overlapping segments of ``nperseg`` samples, each segment's mean
removed, one-sided densities [units^2/Hz], the mean over the segments), without importing
:mod:`scipy.signal`; the same numbers within rounding (``tests/test_dsp.py``).
"""

from __future__ import annotations

import numpy as np


def _segments_spectrum(x: np.ndarray, window: np.ndarray) -> np.ndarray:
    """The rFFT of each half-overlapping, mean-removed segment of ``x`` (1-D), times ``window``
    (its length the segments')."""
    nperseg = window.size
    step = nperseg - nperseg // 2
    starts = np.arange(0, x.size - nperseg + 1, step)
    segments = x[starts[:, None] + np.arange(nperseg)]
    segments = segments - segments.mean(axis=1, keepdims=True)
    return np.fft.rfft(segments * window, n=nperseg, axis=1)


def hann(n: int) -> np.ndarray:
    """The periodic Hann window of ``n`` samples (``scipy.signal.get_window("hann", n)``)."""
    return 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(n) / n)


def csd(x: np.ndarray, y: np.ndarray, fs: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """Cross spectral density of ``x`` and ``y`` (1-D, equal lengths): frequencies [Hz] and
    ``Pxy`` [units_x units_y/Hz], complex; ``scipy.signal.csd(x, y, fs=fs, nperseg=nperseg)``.
    A segment longer than the signals is cut to their length, as scipy does."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.ndim != 1 or x.shape != y.shape:
        raise ValueError(f"csd needs two 1-D signals of one length, got {x.shape} and {y.shape}")
    nperseg = int(min(nperseg, x.size))
    if nperseg < 1:
        raise ValueError("csd needs at least one sample")
    window = hann(nperseg)
    scale = 1.0 / (fs * float((window * window).sum()))
    fx = _segments_spectrum(x, window)
    fy = fx if y is x else _segments_spectrum(y, window)
    p = np.conjugate(fx) * fy * scale
    if nperseg % 2:
        p[:, 1:] *= 2
    else:
        p[:, 1:-1] *= 2
    return np.fft.rfftfreq(nperseg, 1.0 / fs), p.mean(axis=0)


def welch(x: np.ndarray, fs: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """Power spectral density of ``x`` (1-D): frequencies [Hz] and ``Pxx`` [units^2/Hz];
    ``scipy.signal.welch(x, fs=fs, nperseg=nperseg)``."""
    x = np.asarray(x, dtype=float)
    f, p = csd(x, x, fs, nperseg)
    return f, p.real

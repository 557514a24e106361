"""Velocity and acceleration from sampled position, with zero-phase filtering.

Used when a log has position but no velocity (e.g. the EMPS data set). The
position is low-pass filtered forward and backward (``scipy.signal.filtfilt``'s
operations, Butterworth, no phase lag, :mod:`servobench.bench.dsp.iir`) and differentiated by central differences; or,
with ``method="savgol"``, a Savitzky-Golay derivative does both at once. For
inverse-dynamic least squares on the filtered signals, the command and any
other regressor are filtered in parallel with :func:`lowpass` (the IDIM-LS
practice), so the filter cancels from the fitted relation.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from servobench.errors import IdentificationError

#: Default cut-off of the position filter, as a fraction of the sample rate.
CUTOFF_FRACTION = 0.05
#: Butterworth order (applied twice by filtfilt: effective order 8, zero phase).
FILTER_ORDER = 4


@dataclass(frozen=True)
class DerivedMotion:
    """Filtered position [units], velocity [units/s], acceleration [units/s^2]; shape ``(n,)``."""

    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    cutoff_hz: float
    method: str


def default_cutoff_hz(fs_hz: float) -> float:
    """``fs/20`` [Hz]: well above the mechanical band, well below the encoder noise."""
    return CUTOFF_FRACTION * fs_hz


def settle_samples(fs_hz: float, cutoff_hz: float) -> int:
    """Samples at each end that the forward-backward filter's edge transient spoils."""
    return int(math.ceil(3.0 * fs_hz / cutoff_hz))


def butterworth(order: int, wn: float) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.signal.butter(order, wn)``, designed once per order and normalised cut-off (the
    diagnosis filters the same signals thousands of times): :func:`.dsp.iir.butter_lowpass`."""
    from servobench.bench.dsp.iir import butter_lowpass

    return butter_lowpass(order, wn)


@functools.lru_cache(maxsize=64)
def _steady_state(order: int, wn: float) -> np.ndarray:
    """``scipy.signal.lfilter_zi`` of :func:`butterworth` ``(order, wn)``: the filter's state in
    its step response's steady state, solved once (``filtfilt`` solves it on every call)."""
    from servobench.bench.dsp.iir import lfilter_zi

    zi = lfilter_zi(*butterworth(order, wn))
    zi.flags.writeable = False
    return zi


def _filtfilt(order: int, wn: float, y: np.ndarray, axis: int) -> np.ndarray:
    """``scipy.signal.filtfilt(b, a, y, axis=axis)`` (its default odd padding of ``3 * max(len(a),
    len(b))`` samples at each end and steady-state initial conditions), operation for
    operation, with the steady state solved once per filter (:func:`_steady_state`) and both
    passes in one compiled call (:func:`.dsp.iir.filtfilt_padded`, without importing
    :mod:`scipy.signal`)."""
    from servobench.bench.dsp.iir import filtfilt_padded

    b, a = butterworth(order, wn)
    n = 3 * max(len(a), len(b))
    x = np.moveaxis(y, axis, 0)
    shape = x.shape
    x = x.reshape(shape[0], -1)
    ext = np.concatenate((2 * x[:1] - x[n:0:-1], x, 2 * x[-1:] - x[-2 : -(n + 2) : -1]), axis=0)
    out = filtfilt_padded(b, a, _steady_state(order, wn), ext, n)
    return np.moveaxis(out.reshape(shape), 0, axis)


def lowpass(
    y: np.ndarray,
    fs_hz: float,
    cutoff_hz: float | None = None,
    order: int = FILTER_ORDER,
    axis: int = 0,
) -> np.ndarray:
    """Zero-phase Butterworth low-pass of ``y`` along ``axis``.

    ``cutoff_hz`` [Hz] defaults to :func:`default_cutoff_hz`, that of the position filter.
    """
    if cutoff_hz is None:
        cutoff_hz = default_cutoff_hz(fs_hz)
    if not (0 < cutoff_hz < fs_hz / 2):
        raise IdentificationError(
            f"velocity filter cut-off {cutoff_hz} Hz must lie between 0 and Nyquist ({fs_hz / 2} Hz)"
        )
    wn = cutoff_hz / (fs_hz / 2)
    b, a = butterworth(order, wn)
    y = np.asarray(y, dtype=float)
    padlen = 3 * max(len(a), len(b))
    if y.shape[axis] <= padlen:
        raise IdentificationError(f"too few samples ({y.shape[axis]}) to filter the position")
    return _filtfilt(order, wn, y, axis)


def zoh_centered(u: np.ndarray) -> np.ndarray:
    """The held command seen at the sample instants: ``(u[k-1] + u[k]) / 2`` (``u[0]`` at ``k = 0``).

    ``u[k]`` is held over ``[t_k, t_{k+1})``, so its mean over a window centred
    on ``t_k`` is the average of the two neighbouring holds.
    """
    u = np.asarray(u, dtype=float)
    return np.concatenate((u[:1], 0.5 * (u[1:] + u[:-1])))


def filter_command(u: np.ndarray, fs_hz: float, cutoff_hz: float | None = None) -> np.ndarray:
    """The command [command units] as a filtered velocity sees it.

    :func:`zoh_centered`, then the same zero-phase :func:`lowpass` (default cut-off
    :func:`default_cutoff_hz`), so that the filter cancels from the fitted relation.
    """
    return lowpass(zoh_centered(u), fs_hz, cutoff_hz)


def differentiate_position(
    x: np.ndarray,
    fs_hz: float,
    cutoff_hz: float | None = None,
    method: str = "butter",
    t: np.ndarray | None = None,
) -> DerivedMotion:
    """Velocity and acceleration from position.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Position [units] at the sample instants.
    fs_hz : float
        Sample rate [Hz].
    cutoff_hz : float, optional
        Filter cut-off [Hz]; default :func:`default_cutoff_hz`.
    method : {"butter", "savgol"}
        Zero-phase Butterworth plus central differences, or Savitzky-Golay
        (cubic, window about ``fs / cutoff`` samples).
    t : ndarray, optional
        Sample times [s] for central differences on an irregular grid.

    Returns
    -------
    DerivedMotion
    """
    x = np.asarray(x, dtype=float)
    cutoff = default_cutoff_hz(fs_hz) if cutoff_hz is None else float(cutoff_hz)
    dt = 1.0 / fs_hz
    spacing: float | np.ndarray = dt if t is None else np.asarray(t, dtype=float)
    if method == "butter":
        xf = lowpass(x, fs_hz, cutoff)
        v = np.gradient(xf, spacing)
        a = np.gradient(v, spacing)
    elif method == "savgol":
        from scipy.signal import savgol_filter

        window = max(5, int(round(fs_hz / cutoff)) | 1)
        if len(x) <= window:
            raise IdentificationError(
                f"too few samples ({len(x)}) for a {window}-sample derivative"
            )
        xf = savgol_filter(x, window, 3)
        v = savgol_filter(x, window, 3, deriv=1, delta=dt)
        a = savgol_filter(x, window, 3, deriv=2, delta=dt)
    else:
        raise IdentificationError(f"unknown derivative method {method!r} (butter or savgol)")
    return DerivedMotion(xf, v, a, cutoff, method)

"""Periodic multi-frequency binary excitation for SIDBE.

The excitation ``u1`` is a binary signal (values ``+A`` and ``-A``) that
repeats every ``samples_per_period`` samples and puts most of its power on a
chosen set of harmonic lines ``f_k = k * fs / samples_per_period`` [Hz]. It
is designed like a discrete-interval binary sequence (Tan & Godfrey): a
multisine with Schroeder phases on the wanted lines is clipped to its sign,
and the phases of the clipped signal are fed back into the multisine until
the share of power on the wanted lines stops improving. The second SIDBE
experiment applies ``u2 = ratio * u1``.

All frequencies are in Hz, amplitudes in command units.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from servobench.errors import LogFormatError, UsageError

#: Default sample rate [Hz].
DEFAULT_FS_HZ = 1000.0
#: Default period of the excitation [s]; lines are multiples of 1/period.
DEFAULT_PERIOD_S = 4.0
#: Default number of periods per run (the first is discarded as transient).
DEFAULT_PERIODS = 4
#: Default ratio u2/u1 of the two SIDBE runs.
DEFAULT_RATIO = 0.9
#: Default amplitude [command units].
DEFAULT_AMPLITUDE = 1.0
#: Default highest excited line [Hz] (also capped at fs/20).
DEFAULT_F_MAX_HZ = 40.0
#: Number of default lines (log-spaced harmonics, fewer if they coincide).
DEFAULT_LINES = 16
#: Sign-clipping iterations of the binary design.
DESIGN_ITERATIONS = 60
#: Relative tolerance for "frequency is a harmonic of 1/period".
COMMENSURATE_RTOL = 1e-6


@dataclass(frozen=True)
class ExcitationDesign:
    """What was (or will be) applied: enough for ``identify`` to find the lines again.

    Attributes
    ----------
    fs_hz : float
        Sample (cycle) rate [Hz].
    samples_per_period : int
        Samples in one period of ``u1``.
    periods : int
        Periods per run (>= 2; the first is the transient).
    freqs_hz : tuple of float
        Excited lines [Hz], harmonics of ``fs_hz / samples_per_period``.
    amplitude : float
        Level ``A`` of ``u1`` [command units].
    ratio : float
        ``u2 = ratio * u1``, ``0 < ratio < 1``.
    """

    fs_hz: float
    samples_per_period: int
    periods: int
    freqs_hz: tuple[float, ...]
    amplitude: float
    ratio: float = DEFAULT_RATIO

    def __post_init__(self) -> None:
        validate(self.amplitude, self.ratio, self.fs_hz, self.periods)
        if self.samples_per_period < 4:
            raise UsageError("a period needs at least 4 samples")
        harmonics(self.freqs_hz, self.fs_hz, self.samples_per_period)

    @property
    def period_s(self) -> float:
        return self.samples_per_period / self.fs_hz

    @property
    def lines(self) -> np.ndarray:
        """Harmonic indices ``k`` of the excited lines (DFT bins of one period)."""
        return harmonics(self.freqs_hz, self.fs_hz, self.samples_per_period)

    @property
    def samples_per_run(self) -> int:
        return self.samples_per_period * self.periods

    def with_amplitude(self, amplitude: float) -> ExcitationDesign:
        return ExcitationDesign(
            self.fs_hz, self.samples_per_period, self.periods, self.freqs_hz, amplitude, self.ratio
        )

    def with_freqs(self, freqs_hz: Sequence[float]) -> ExcitationDesign:
        return ExcitationDesign(
            self.fs_hz,
            self.samples_per_period,
            self.periods,
            tuple(freqs_hz),
            self.amplitude,
            self.ratio,
        )

    def with_periods(self, periods: int) -> ExcitationDesign:
        return ExcitationDesign(
            self.fs_hz, self.samples_per_period, periods, self.freqs_hz, self.amplitude, self.ratio
        )

    def metadata(self) -> dict[str, object]:
        """``# key = value`` lines for the log header (read back by :func:`design_from_metadata`)."""
        return {
            "fs": self.fs_hz,
            "amplitude": self.amplitude,
            "ratio": self.ratio,
            "freqs": [float(f) for f in self.freqs_hz],
            "periods": self.periods,
            "samples_per_period": self.samples_per_period,
            "excitation": "periodic binary multisine (SIDBE); run 1 = u1, run 2 = ratio * u1",
        }


@dataclass(frozen=True)
class Excitation:
    """The two SIDBE commands of one design, arrays of shape ``(periods * samples_per_period,)``."""

    design: ExcitationDesign
    u1: np.ndarray
    u2: np.ndarray
    line_power_share: float

    def runs(self) -> list[tuple[int, np.ndarray]]:
        """``[(1, u1), (2, u2)]`` as :func:`servobench.bench.run.runner.stream_runs` takes them."""
        return [(1, self.u1), (2, self.u2)]


def validate(amplitude: float, ratio: float, fs_hz: float, periods: int) -> None:
    """Raise :class:`UsageError` for out-of-range excitation options."""
    if not (math.isfinite(amplitude) and amplitude > 0):
        raise UsageError(f"amplitude must be > 0, got {amplitude}")
    if not (math.isfinite(ratio) and 0 < ratio < 1):
        raise UsageError(f"ratio must satisfy 0 < ratio < 1, got {ratio}")
    if not (math.isfinite(fs_hz) and fs_hz > 0):
        raise UsageError(f"fs must be > 0 Hz, got {fs_hz}")
    if int(periods) != periods or periods < 2:
        raise UsageError(f"periods must be an integer >= 2, got {periods}")


def harmonics(freqs_hz: Sequence[float], fs_hz: float, samples_per_period: int) -> np.ndarray:
    """Harmonic indices of ``freqs_hz``; :class:`UsageError` unless each is a positive harmonic below Nyquist."""
    freqs = np.asarray(list(freqs_hz), dtype=float)
    if freqs.size == 0:
        raise UsageError("at least one excitation frequency is needed")
    period_s = samples_per_period / fs_hz
    out = []
    for f in freqs:
        if not (math.isfinite(f) and f > 0):
            raise UsageError(f"excitation frequencies must be > 0 Hz, got {f}")
        if f >= fs_hz / 2:
            raise UsageError(f"excitation frequency {f} Hz is not below Nyquist ({fs_hz / 2} Hz)")
        k = f * period_s
        if abs(k - round(k)) > COMMENSURATE_RTOL * max(1.0, k):
            raise UsageError(
                f"excitation frequency {f} Hz is not a multiple of 1/period = {1 / period_s:.6g} Hz"
            )
        out.append(int(round(k)))
    lines = np.array(sorted(set(out)), dtype=int)
    if lines.size != len(out):
        raise UsageError("excitation frequencies repeat")
    return lines


def default_freqs(
    fs_hz: float, samples_per_period: int, count: int = DEFAULT_LINES
) -> tuple[float, ...]:
    """Log-spaced harmonic lines from ``1/period`` up to ``min(40 Hz, fs/20)``."""
    return freqs_from(fs_hz / samples_per_period, fs_hz, samples_per_period, count)


def top_line_hz(fs_hz: float, samples_per_period: int) -> float:
    """The highest default line [Hz]: ``min(40 Hz, fs/20)``, at least ``1/period``."""
    f0 = fs_hz / samples_per_period
    return max(1, int(min(DEFAULT_F_MAX_HZ, fs_hz / 20) / f0)) * f0


def freqs_from(
    lowest_hz: float, fs_hz: float, samples_per_period: int, count: int = DEFAULT_LINES
) -> tuple[float, ...]:
    """Log-spaced harmonic lines from ``lowest_hz`` up to ``min(40 Hz, fs/20)``.

    The design of an axis with limited travel: the lowest line is raised until
    the travel it drives fits the window (:mod:`servobench.bench.run.travel`).
    ``lowest_hz`` is rounded to a harmonic of ``1/period``; when it is at or
    above the top line, that one line is returned.
    """
    f0 = fs_hz / samples_per_period
    k_max = int(round(top_line_hz(fs_hz, samples_per_period) / f0))
    k_lo = min(max(1, int(round(lowest_hz / f0))), k_max)
    ks = np.unique(np.round(np.geomspace(k_lo, k_max, count)).astype(int))
    return tuple(float(k * f0) for k in ks)


def lowest_line_choices(fs_hz: float, samples_per_period: int, lines: int = 4) -> tuple[float, ...]:
    """Candidate lowest lines [Hz], ascending: harmonics spaced by about 20 %, from
    ``1/period`` up to where at least ``lines`` lines still fit below the top line."""
    f0 = fs_hz / samples_per_period
    k_top = int(round(top_line_hz(fs_hz, samples_per_period) / f0))
    k_hi = max(1, k_top // lines)
    ks = np.unique(np.round(np.geomspace(1, k_hi, max(2, int(np.log(k_hi) / np.log(1.2)) + 1))))
    return tuple(float(k * f0) for k in ks.astype(int))


def freqs_around(
    corner_hz: float, fs_hz: float, samples_per_period: int, count: int = DEFAULT_LINES
) -> tuple[float, ...]:
    """Lines log-spaced over two decades centred on ``corner_hz`` (the redesign of SIDBE step 6).

    The corner is first clamped to what the period and sample rate can carry
    (``[1/period, fs/40]``); the lines stay below ``fs/4``.
    """
    f0 = fs_hz / samples_per_period
    k_top = max(2, int(fs_hz / 4 / f0))
    corner = min(max(corner_hz, f0), fs_hz / 40) if math.isfinite(corner_hz) else 10 * f0
    k_lo = max(1, int(math.floor(corner / 10 / f0)))
    k_hi = max(k_lo + 1, min(int(corner * 10 / f0), k_top))
    k_lo = min(k_lo, k_hi - 1)
    ks = np.unique(np.round(np.geomspace(k_lo, k_hi, count)).astype(int))
    return tuple(float(k * f0) for k in ks)


def samples_for_period(fs_hz: float, period_s: float) -> int:
    """Samples per period for ``period_s`` [s] at ``fs_hz`` (UsageError when below 4)."""
    if not (math.isfinite(period_s) and period_s > 0):
        raise UsageError(f"period must be > 0 s, got {period_s}")
    n = int(round(period_s * fs_hz))
    if n < 4:
        raise UsageError(f"period {period_s} s holds fewer than 4 samples at {fs_hz} Hz")
    return n


def make_design(
    amplitude: float = DEFAULT_AMPLITUDE,
    *,
    ratio: float = DEFAULT_RATIO,
    fs_hz: float = DEFAULT_FS_HZ,
    periods: int = DEFAULT_PERIODS,
    period_s: float = DEFAULT_PERIOD_S,
    freqs_hz: Sequence[float] | None = None,
) -> ExcitationDesign:
    """Validate the options and build an :class:`ExcitationDesign` (default lines when ``freqs_hz`` is None)."""
    validate(amplitude, ratio, fs_hz, periods)
    n = samples_for_period(fs_hz, period_s)
    freqs = tuple(freqs_hz) if freqs_hz else default_freqs(fs_hz, n)
    return ExcitationDesign(float(fs_hz), n, int(periods), freqs, float(amplitude), float(ratio))


def binary_period(
    samples: int, lines: np.ndarray, iterations: int = DESIGN_ITERATIONS
) -> tuple[np.ndarray, float]:
    """One period of a ±1 signal with its power concentrated on DFT bins ``lines``.

    Returns the period (shape ``(samples,)``) and the share of its AC power on
    the wanted lines. Deterministic: Schroeder phases start the iteration.
    """
    lines = np.asarray(lines, dtype=int)
    m = lines.size
    phases = -np.pi * np.arange(m) * (np.arange(m) + 1) / m  # Schroeder
    best, best_share = np.ones(samples), -1.0
    previous = None
    spec = np.zeros(samples // 2 + 1, dtype=complex)
    for _ in range(max(1, iterations)):
        spec[:] = 0.0
        spec[lines] = np.exp(1j * phases)
        s = np.where(np.fft.irfft(spec, samples) >= 0, 1.0, -1.0)
        if previous is not None and np.array_equal(s, previous):
            break  # converged
        s_spec = np.fft.rfft(s)
        power = float(np.sum(np.abs(s_spec[1:]) ** 2))
        share = float(np.sum(np.abs(s_spec[lines]) ** 2)) / power if power else 0.0
        if share > best_share:
            best, best_share = s, share
        previous = s
        phases = np.angle(s_spec[lines])
    return best, best_share


def design_excitation(design: ExcitationDesign) -> Excitation:
    """The commands ``u1`` (``±amplitude``) and ``u2 = ratio * u1`` of a design."""
    period, share = binary_period(design.samples_per_period, design.lines)
    u1 = design.amplitude * np.tile(period, design.periods)
    return Excitation(design, u1, design.ratio * u1, share)


def design_from_metadata(
    metadata: Mapping[str, str], fs_hz: float, source: str = "log"
) -> ExcitationDesign | None:
    """The excitation a log's metadata describes, or None when it names none.

    Raises
    ------
    LogFormatError
        The excitation keys are present but malformed.
    """
    if "samples_per_period" not in metadata or "freqs" not in metadata:
        return None
    try:
        n = int(float(metadata["samples_per_period"]))
        freqs = tuple(float(f) for f in metadata["freqs"].split(",") if f.strip())
        periods = int(float(metadata.get("periods", "2")))
        amplitude = float(metadata.get("amplitude", "1"))
        ratio = float(metadata.get("ratio", str(DEFAULT_RATIO)))
        return ExcitationDesign(
            float(metadata.get("fs", fs_hz)), n, periods, freqs, amplitude, ratio
        )
    except (ValueError, UsageError) as err:
        raise LogFormatError(f"{source}: bad excitation metadata ({err})") from None

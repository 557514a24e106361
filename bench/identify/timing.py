"""The timing figure of an identification: how well the host kept time, and what it costs the model.

A real-time log (``pace = real``) states where its instants come from
(``# clock_source = drive | kernel | host``), each sample's timing
uncertainty (column ``t_unc``, the half-width of the interval known to hold
its instant), and the host's cycle in its trailer (``host_jitter_p50_s``,
``host_jitter_p99_s``, ``host_jitter_max_s``, ``missed_cycles``,
``late_cycles``). :func:`timing_figure` turns them into a
:class:`TimingFigure` with the model error this timing predicts:

* **how** -- the model is identified again :data:`DRAWS` times with every
  instant moved at random (an explicit seeded generator) by the estimator
  that gave it. The move is as large as the log shows its instants really
  stray: ``t_unc`` bounds each instant, but a drive that samples at a steady
  point of a wide bracket strays far less (a constant delay moves every
  instant and command alike), so the scatter is read from the model's
  residuals in the transients
  (:func:`~servobench.bench.identify.joint.instant_scatter_s`,
  ``instant_scatter_s`` in the figure) and each instant moves by a normal
  draw of that spread, never beyond ``t +- t_unc``; where the residuals show
  no scatter to read, uniformly within ``t +- t_unc``. Served Modbus RTU
  without its time stamp at 50 Hz: brackets 1.2 ms wide either way, a
  scatter of 0.03 ms read, a predicted M error of 0.1 % against the 0.1 %
  measured (the bracket alone predicted 1.1 %). The re-run estimator: an output-error model is refined again from itself on each moved copy;
  any other by the joint estimator's exact pair regression
  (:func:`~servobench.bench.identify.joint.pair_regression`, weighted by the
  timing uncertainty), compared with the same regression on the instants as
  logged. The root mean square
  of the relative change of each parameter over the draws is its predicted
  timing error [%] (1 sigma). The draws cover the excited band as the log
  does: they perturb the very samples the model comes from.
* A drive time stamp (``clock_source = drive``) has no interval: the
  predicted error is 0, whatever the host's jitter (the instants are exact).

A figure whose largest parameter error exceeds the stated accuracy
(:data:`ACCURACY_PCT`) is not :attr:`TimingFigure.within_accuracy`; its
:meth:`TimingFigure.advice` says what to change: a lower ``--fs``, a free
core, a drive that time-stamps its samples.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from servobench.bench.identify.dataset import Dataset
from servobench.bench.identify.estimate import MethodEstimate
from servobench.bench.model.servo import STD_KEYS
from servobench.errors import IdentificationError

#: Accuracy the model states for its parameters [%]: timing that predicts more is reported.
ACCURACY_PCT = 1.0
#: Re-identifications with perturbed instants.
DRAWS = 4
#: Seed of the perturbations (the figure is reproducible from the log).
SEED = 22
#: Metadata keys of the host's cycle (the runner's trailer).
CYCLE_KEYS = ("host_jitter_p50_s", "host_jitter_p99_s", "host_jitter_max_s", "missed_cycles",
              "late_cycles", "t_unc_p50_s", "t_unc_p99_s", "t_unc_max_s")  # fmt: skip
METHOD = (
    f"re-identification ({DRAWS} draws, by the estimator that gave the model) with every instant "
    "moved at random by the scatter the residuals show (instant_scatter_s, normal), never beyond "
    "its uncertainty t_unc; rms relative change, 1 sigma"
)
#: The method where the residuals show no scatter to read.
METHOD_BOUND = (
    f"re-identification ({DRAWS} draws, by the estimator that gave the model) with every instant "
    "moved at random within its uncertainty t_unc; rms relative change, 1 sigma"
)


@dataclass(frozen=True)
class TimingFigure:
    """How well the instants of a real-time log are known, and the model error that predicts.

    Attributes
    ----------
    clock_source : str
        ``drive``, ``kernel`` or ``host``.
    cycle : mapping of str to float
        The host's cycle from the log trailer (:data:`CYCLE_KEYS`, seconds and counts).
    fs_hz : float
        The log's cycle rate [Hz].
    model_error_pct : mapping of str to float
        Predicted timing error of ``M``, ``B``, ``coulomb_pos``, ``coulomb_neg`` [%], 1 sigma.
    method : str
        How the error was predicted.
    accuracy_pct : float
        The accuracy the model states [%].
    """

    clock_source: str
    cycle: Mapping[str, float]
    fs_hz: float
    model_error_pct: Mapping[str, float] = field(default_factory=dict)
    method: str = METHOD
    accuracy_pct: float = ACCURACY_PCT
    time_constant_s: float = math.nan  #: the model's ``M / B`` [s]
    link_max_hz: float = math.nan  #: the rate the link carries, from the log [Hz]
    #: How far the instants stray, 1 sigma each, as the residuals show [s] (NaN: not read).
    instant_scatter_s: float = math.nan

    @property
    def model_error_max_pct(self) -> float:
        values = [v for v in self.model_error_pct.values() if math.isfinite(v)]
        return max(values) if values else 0.0

    @property
    def within_accuracy(self) -> bool:
        return self.model_error_max_pct <= self.accuracy_pct

    def advice(self) -> list[str]:
        """What to change, most effective first (empty when within accuracy)."""
        if self.within_accuracy:
            return []
        if self.time_constant_s < 2.0 / self.fs_hz:  # the cycle is long against the plant
            carries = f" (the link carries {self.link_max_hz:.0f} Hz)" if math.isfinite(self.link_max_hz) else ""
            tips = [f"raise --fs where the link allows{carries}: the plant's time constant "
                    f"{self.time_constant_s * 1e3:.3g} ms is short against the {1e3 / self.fs_hz:.3g} ms "
                    "cycle, so the instants' uncertainty weighs on M"]  # fmt: skip
        else:
            lower = _nice_below(self.fs_hz / 2)
            tips = [f"lower --fs (e.g. --fs {lower:g}: longer cycles, the same timing error weighs less)"]
        load = _load_average()
        tips.append(
            "free a core for the host" + (f" (load average {load:.1f})" if load is not None else "")
        )
        if self.clock_source != "drive":
            tips.append("use a drive that time-stamps its samples (CiA 402 0x1013 mapped, a Modbus "
                        "map with a time-stamp register): its instants are exact")  # fmt: skip
        return tips

    def warning_lines(self) -> list[str]:
        """The lines a summary starts with when the timing takes the model outside its accuracy."""
        if self.within_accuracy:
            return []
        worst = max(self.model_error_pct, key=lambda k: self.model_error_pct[k])
        c = self.cycle
        first = (
            f"WARNING: timing takes the model outside its stated accuracy: {worst} may be off by "
            f"{self.model_error_pct[worst]:.2g} % (1 sigma; stated accuracy {self.accuracy_pct:g} %), "
            f"clock_source = {self.clock_source}, instants uncertain by up to "
            f"{_ms(c.get('t_unc_p99_s'))} ms (p99), host jitter p99 {_ms(c.get('host_jitter_p99_s'))} ms, "
            f"{int(c.get('missed_cycles', 0) or 0)} missed cycles"
        )
        return [first, "to change: " + "; ".join(self.advice())]

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"clock_source": self.clock_source}
        for key in CYCLE_KEYS:
            value = _finite(self.cycle.get(key, math.nan))
            counted = key.endswith("_cycles") and value is not None
            out[key.replace("host_", "")] = int(value) if counted else value
        out.update(
            model_error_pct={k: _finite(v) for k, v in self.model_error_pct.items()},
            model_error_max_pct=_finite(self.model_error_max_pct),
            model_error_method=self.method,
            instant_scatter_s=_finite(self.instant_scatter_s),
            accuracy_pct=self.accuracy_pct,
            within_accuracy=self.within_accuracy,
            advice=self.advice(),
        )
        return out


def _finite(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def _ms(value: float | None) -> str:
    return "?" if value is None or not math.isfinite(value) else f"{value * 1e3:.3g}"


def _nice_below(fs_hz: float) -> float:
    decade = 10.0 ** math.floor(math.log10(max(fs_hz, 1.0)))
    return max(m * decade for m in (1.0, 2.0, 2.5, 5.0) if m * decade <= max(fs_hz, 1.0))


def _load_average() -> float | None:
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def _number(text: str | None) -> float:
    try:
        return float(text) if text is not None else math.nan
    except ValueError:
        return math.nan


def timing_figure(
    metadata: Mapping[str, str], data: Dataset, estimate: MethodEstimate
) -> TimingFigure | None:
    """The timing figure of a real-time log and the model identified from it.

    None for a log without ``clock_source`` (lock-step streaming, older logs,
    files of other tools): its instants are the nominal grid or the drive's.
    """
    source = metadata.get("clock_source", "").strip()
    if not source:
        return None
    cycle = {key: _number(metadata.get(key)) for key in CYCLE_KEYS}
    error = {k: 0.0 for k in STD_KEYS}
    scatter, method = math.nan, METHOD
    if data.timing_uncertain and not data.derived:
        from servobench.bench.identify.joint import instant_scatter_s

        scatter = instant_scatter_s(data, estimate.model)
        error = perturbed_spread_pct(data, estimate, scatter_s=scatter)
        method = METHOD if math.isfinite(scatter) else METHOD_BOUND
    m = estimate.model
    tau = m.M / m.B if m.B > 0 else math.inf
    return TimingFigure(source, cycle, data.fs_hz, error, method=method, time_constant_s=tau,
                        link_max_hz=_number(metadata.get("link_max_rate_hz")),
                        instant_scatter_s=scatter)  # fmt: skip


def perturbed_spread_pct(
    data: Dataset,
    estimate: MethodEstimate,
    draws: int = DRAWS,
    seed: int = SEED,
    scatter_s: float = math.nan,
) -> dict[str, float]:
    """RMS relative change [%] of each parameter when the instants move within ``t_unc``:
    by normal draws of ``scatter_s`` [s] clipped to ``t +- t_unc``, or uniformly within it
    when ``scatter_s`` is NaN.

    The estimator of ``estimate`` is re-run: an output-error estimate is refined
    again from itself on each perturbed copy (the refinement alone, started where
    it ended); any other by the joint pair regression, compared with the same
    regression on the instants as logged.
    """
    from servobench.bench.identify.joint import identify_joint, pair_regression

    rng = np.random.default_rng(seed)
    refine = estimate.estimator.endswith("output-error")
    model = estimate.model
    if not refine:
        with contextlib.suppress(IdentificationError):  # the same estimator on the instants as logged
            model = pair_regression(data)
    nominal = np.array([model.M, model.B, model.coulomb_pos, model.coulomb_neg])
    changes = []
    for _ in range(draws):
        segments = []
        for s in data.segments:
            if s.t_unc is None:
                segments.append(s)
                continue
            if math.isfinite(scatter_s):
                t = s.t + np.clip(rng.normal(0.0, scatter_s, len(s)), -s.t_unc, s.t_unc)
            else:
                t = s.t + rng.uniform(-1.0, 1.0, len(s)) * s.t_unc
            dt = np.diff(t)
            if not np.all(dt > 0):  # overlapping intervals (not a runner's log): move less
                t = s.t + 0.5 * rng.uniform(-1.0, 1.0, len(s)) * np.minimum(
                    s.t_unc, np.concatenate(([np.inf], np.diff(s.t))), )
                dt = np.diff(t)
            segments.append(replace(s, t=t, dt_s=np.maximum(dt, 1e-12)))
        moved = replace(data, segments=tuple(segments))
        try:
            m = identify_joint(moved, start=estimate).model if refine else pair_regression(moved)
        except IdentificationError:
            continue
        values = np.array([m.M, m.B, m.coulomb_pos, m.coulomb_neg])
        with np.errstate(divide="ignore", invalid="ignore"):
            changes.append(np.where(nominal != 0, values / nominal - 1.0, 0.0))
    if not changes:
        return {k: math.inf for k in STD_KEYS}
    rms = np.sqrt(np.mean(np.square(changes), axis=0)) * 100.0
    return dict(zip(STD_KEYS, (float(x) for x in rms), strict=True))

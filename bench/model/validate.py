"""Validate a saved model against another log: ``fit_percent``, ``gap_percent``, ``force_error_percent``.

The figures are those ``identify`` and ``diagnose`` report, computed by their code:

* ``fit_percent`` -- ``identify``'s verification fit,
  ``100 (1 - ||v - v_sim|| / ||v - mean(v)||)`` over all runs, ``v_sim`` the
  model simulated over each whole run on the logged command from the run's
  initial velocity (:func:`servobench.bench.identify.verify.verify`; with
  effects, the simulator ``diagnose`` uses);
* ``gap_percent`` -- ``diagnose``'s velocity gap, the NRMSE
  ``100 rms(v_sim - v) / std(v)`` of its comparison: whole-run simulation for
  open-loop logs, predictions restarted from the measured state every
  0.5 s for closed-loop ones (:mod:`servobench.bench.diagnose.data`);
* ``force_error_percent`` (closed-loop logs only) -- the relative force error
  of the EMPS reference, ``100 ||u - u_hat|| / ||u||``, ``u_hat`` the inverse
  model on the measured motion. Velocity and acceleration come from the
  position through ``identify``'s zero-phase filter, and ``u`` passes the
  same filter (as in IDIM-LS), so the filter cancels; the filter's settling
  samples at each end are left out. The effects' own terms enter the inverse
  model (command transforms, delay, direction-dependent viscous friction,
  friction excess, position forces); a coupled second body (``resonance``,
  ``backlash``) has no inverse-dynamic form and is left out, with a note.

Pure: a model and a log in, a frozen :class:`Validation` out.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from servobench.bench.blas_threads import on_one_blas_thread
from servobench.bench.diagnose.data import DiagnosisData, prepare
from servobench.bench.diagnose.simulate import Candidate, gap_percent, simulate
from servobench.bench.identify.dataset import Segment
from servobench.bench.identify.derivative import (
    differentiate_position,
    filter_command,
    settle_samples,
)
from servobench.bench.identify.verify import verify
from servobench.bench.log.io import ExperimentLog
from servobench.bench.model.servo import ServoModel, fit_percent
from servobench.errors import IdentificationError, UsageError
from servobench.sim_backend.physics.coulomb import PlantParams
from servobench.sim_backend.physics.effects import collect_terms
from servobench.units import SignalUnits


@dataclass(frozen=True)
class RunComparison:
    """One run, arrays of shape ``(n,)``: times [s], measured and simulated velocity [units/s],
    and for closed-loop logs the filtered command and the inverse model's command [command units]
    (NaN where the filter settles)."""

    run: int
    t: np.ndarray
    v: np.ndarray
    v_sim: np.ndarray
    u_f: np.ndarray | None = None
    u_hat: np.ndarray | None = None


@dataclass(frozen=True)
class Validation:
    """How well a model reproduces a log; see the module docstring for the figures [%]."""

    samples: int
    fit_percent: float
    gap_percent: float
    force_error_percent: float | None
    closed_loop: bool
    comparison: str
    runs: tuple[RunComparison, ...]
    notes: tuple[str, ...] = ()

    def to_json(self) -> dict[str, object]:
        out: dict[str, object] = {
            "fit_percent": _finite(self.fit_percent),
            "gap_percent": _finite(self.gap_percent),
        }
        if self.force_error_percent is not None:
            out["force_error_percent"] = _finite(self.force_error_percent)
        out.update({
            "samples": self.samples,
            "runs": len(self.runs),
            "loop": "closed" if self.closed_loop else "open",
            "comparison": self.comparison,
            "notes": list(self.notes),
        })  # fmt: skip
        return out


#: Default thresholds of ``servobench validate``: the SIDBE verification threshold, and the
#: velocity gap that leaves the same share of the motion unexplained.
DEFAULT_MIN_FIT_PERCENT = 90.0
DEFAULT_MAX_GAP_PERCENT = 10.0


@dataclass(frozen=True)
class Judgement:
    """A validation against thresholds: ``passed`` and one clause per figure judged."""

    passed: bool
    clauses: tuple[str, ...]
    min_fit_percent: float
    max_gap_percent: float

    def text(self) -> str:
        return ", ".join(self.clauses)

    def as_dict(self) -> dict[str, float]:
        return {"min_fit_percent": self.min_fit_percent, "max_gap_percent": self.max_gap_percent}


def judge(
    result: Validation,
    min_fit_percent: float = DEFAULT_MIN_FIT_PERCENT,
    max_gap_percent: float = DEFAULT_MAX_GAP_PERCENT,
) -> Judgement:
    """Pass when ``fit_percent >= min_fit_percent`` and ``gap_percent <= max_gap_percent``
    (a figure that could not be computed fails)."""
    fit, gap = result.fit_percent, result.gap_percent
    fit_ok = bool(np.isfinite(fit) and fit >= min_fit_percent)
    gap_ok = bool(np.isfinite(gap) and gap <= max_gap_percent)
    clauses = (
        f"fit {fit:.2f} % {'>=' if fit_ok else 'below'} {min_fit_percent:g} %",
        f"gap {gap:.2f} % {'<=' if gap_ok else 'above'} {max_gap_percent:g} %",
    )
    return Judgement(fit_ok and gap_ok, clauses, min_fit_percent, max_gap_percent)


def unit_mismatch(model_units: Mapping[str, str], log_units: SignalUnits) -> str:
    """A note when the model's signal units (its ``units`` object) differ from the log's, else ``""``."""
    differ = [
        f"{k}: model [{model_units[k]}], log [{getattr(log_units, k)}]"
        for k in ("u", "v", "x")
        if model_units.get(k) and getattr(log_units, k) and model_units[k] != getattr(log_units, k)
    ]
    return ("units differ, the figures compare numbers in different units (" + "; ".join(differ) + ")"
            if differ else "")  # fmt: skip


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


@on_one_blas_thread
def validate(
    model: ServoModel,
    log: ExperimentLog,
    effects: Mapping[str, Mapping[str, float]] | None = None,
    loop: str | None = None,
) -> Validation:
    """Compare ``model`` (with ``effects``) with ``log``.

    Parameters
    ----------
    model : ServoModel
    log : ExperimentLog
    effects : mapping, optional
        ``{effect: {parameter: value}}`` as ``diagnose`` names them.
    loop : {"open", "closed"}, optional
        Overrides the log's ``loop`` metadata.

    Raises
    ------
    IdentificationError
        The log cannot be compared (too short, nothing moves).
    UsageError
        Bad ``loop``, or effect parameters the simulator rejects.
    """
    if loop is not None:
        if loop not in ("open", "closed"):
            raise UsageError(f"loop must be 'open' or 'closed', got {loop!r}")
        log = replace(log, metadata={**log.metadata, "loop": loop})
    effects = {k: dict(v) for k, v in (effects or {}).items()}
    if model.delay_s > 0 and "time_delay" not in effects:
        # the drive's action delay of the model, in the simulator's terms: u(t - delay)
        effects = {"time_delay": {"delay": model.delay_s}, **effects}
    data = prepare(log)
    candidate = Candidate(
        {"M": model.M, "B": model.B, "coulomb_pos": model.coulomb_pos, "coulomb_neg": model.coulomb_neg},
        effects,
    )
    notes: list[str] = list(data.prepared.notes)
    if set(effects) - {"time_delay"}:
        whole = replace(data, horizon_s=None, starts=tuple(np.array([0]) for _ in data.segments))
        v_sim = simulate(whole, candidate)
    else:
        v_sim = [r.v_sim for r in verify(model, data.prepared, data.sigma_v).runs]
    measured = np.concatenate([s.v for s in data.segments])
    fit = fit_percent(measured, np.concatenate(v_sim))
    if data.horizon_s is None:
        gap = gap_percent(data, v_sim)
    else:
        gap = gap_percent(data, simulate(data, candidate))
        if model.resonance is not None:
            notes.append("the restarted predictions of gap_percent leave the series resonance out")
    closed = bool(data.prepared.closed_loop)
    force_error, forces = None, [(None, None)] * len(data.segments)
    if closed:
        force_error, forces, force_notes = force_error_percent(model, effects, data)
        notes.extend(force_notes)
    runs = tuple(
        RunComparison(s.run, s.t, s.v, vs, uf, uh)
        for s, vs, (uf, uh) in zip(data.segments, v_sim, forces, strict=True)
    )
    samples = int(sum(len(s) for s in data.segments))
    return Validation(samples, fit, gap, force_error, closed, _comparison(data), runs, tuple(notes))


def _comparison(data: DiagnosisData) -> str:
    if data.horizon_s is None:
        return "simulation over each whole run"
    return (f"fit: simulation over each whole run; gap: predictions restarted from the measured "
            f"state every {data.horizon_s:g} s")  # fmt: skip


def force_error_percent(
    model: ServoModel, effects: Mapping[str, Mapping[str, float]], data: DiagnosisData
) -> tuple[float, list[tuple[np.ndarray, np.ndarray]], list[str]]:
    """``100 ||u_f - u_hat|| / ||u_f||`` over all runs, the per-run ``(u_f, u_hat)``, notes."""
    params = PlantParams(M=model.M, B=model.B, coulomb_pos=model.coulomb_pos,
                         coulomb_neg=model.coulomb_neg, effects={k: dict(v) for k, v in effects.items()})  # fmt: skip
    try:
        terms = collect_terms(params)
    except UsageError as err:
        raise UsageError(f"the model's effects cannot be evaluated: {err}") from None
    notes = []
    if terms.coupling is not None:
        notes.append("force_error_percent: the coupled second body of "
                     f"{', '.join(n for n in effects if n in ('resonance', 'backlash'))} "
                     "has no inverse-dynamic form and is left out")  # fmt: skip
    errs, refs, out = [], [], []
    for seg in data.segments:
        u_f, u_hat, keep = _inverse_run(seg, params, terms, data.fs_hz)
        errs.append((u_f - u_hat)[keep])
        refs.append(u_f[keep])
        out.append((np.where(keep, u_f, np.nan), np.where(keep, u_hat, np.nan)))
    err, ref = np.concatenate(errs), np.concatenate(refs)
    if err.size == 0 or not np.any(ref != 0):
        raise IdentificationError("the closed-loop log is too short for the force comparison")
    return 100.0 * float(np.linalg.norm(err) / np.linalg.norm(ref)), out, notes


def _inverse_run(seg: Segment, params: PlantParams, terms, fs_hz: float):
    """Filtered command, the inverse model's command on the filtered motion, the samples compared."""
    motion = seg.motion or differentiate_position(seg.position, fs_hz)
    v, a = motion.v, motion.a
    u_raw = np.asarray(seg.u, dtype=float)
    u = u_raw
    shift = int(round(terms.delay_s * fs_hz))
    if shift:
        u = np.concatenate((np.full(shift, u[0]), u[:-shift]))
    for _, fn in sorted(terms.inputs, key=lambda item: item[0]):
        u = np.asarray(fn(u), dtype=float)
    u_eff = filter_command(u, fs_hz, motion.cutoff_hz)  # the force the model's body feels
    u_f = filter_command(u_raw, fs_hz, motion.cutoff_hz)
    direction = np.sign(v)
    viscous = (params.B + terms.dB * direction) * v
    coulomb = np.where(v > 0, params.coulomb_pos, np.where(v < 0, -params.coulomb_neg, 0.0))
    u_hat = params.M * a + viscous + coulomb
    if terms.friction_excess is not None:
        excess = np.vectorize(terms.friction_excess, otypes=[float])
        u_hat = u_hat + direction * excess(np.abs(v), direction.astype(int))
    x = motion.x if seg.motion is not None else seg.position
    for force in terms.position_forces:
        u_hat = u_hat + np.vectorize(force, otypes=[float])(x)
    u_hat = u_f - (u_eff - u_hat)  # the command that force takes, in the log's command
    edge = settle_samples(fs_hz, motion.cutoff_hz)
    keep = np.zeros(len(u), dtype=bool)
    keep[edge : len(u) - edge] = True
    return u_f, u_hat, keep

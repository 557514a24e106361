"""Outputs of a diagnosis: the JSON object, ``model.json``, ``comparison.csv`` and ``report.md``.

Everything here consumes a :class:`~servobench.bench.diagnose.workflow.Diagnosis`.
One set of numbers: every parameter printed is the final model's (base
refitted with the effects), beside the base fit from before any effect,
labelled as such; the evidence sentences carry no parameter values of
their own. The text output and the report lead with the verdict.
``model.json`` is described in :mod:`servobench.bench.diagnose.model_file`.

Every fitted parameter carries its 1-sigma (:mod:`servobench.bench.diagnose.sigma`): the
JSON's ``std`` (keyed as ``units``: the base as ``base_after`` gives it, ``pole``,
``dc_gain``, and ``"effect.parameter"`` as each effect's ``parameters`` report it, e.g.
``stribeck.fs_pos``; ``delay_s`` beside ``time_delay.delay`` where a delay was named: the
``delay_s`` of ``base_after``, the diagnosed model's action delay, absent without one),
``value ± sigma`` in the text, a 1-sigma column in the report's table.
Parameters held fixed in the fit have none; a coloured training residual is noted.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from servobench.bench.diagnose.model_file import (
    delay_of,
    model_record,
    parameter_units,
    record_std,
    sim_url,
    written_parameters,
)
from servobench.bench.diagnose.sigma import NOISE_MODEL, candidate_std
from servobench.bench.diagnose.simulate import Candidate
from servobench.bench.diagnose.verdict import LABELS
from servobench.bench.diagnose.workflow import (
    Diagnosis,
    companion_force,
    named_parameters,
    net_base,
)

MODEL_FILE = "model.json"
REPORT_FILE = "report.md"
COMPARISON_FILE = "comparison.csv"
#: The base values the text and the report show.
_BASE_SHOWN = ("M", "B", "coulomb_pos", "coulomb_neg", "pole", "dc_gain")


def _clean(value):
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, (np.floating, float)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _base_json(base) -> dict:
    b = {k: float(base[k]) for k in ("M", "B", "coulomb_pos", "coulomb_neg")}
    return {**b, "pole": -b["B"] / b["M"], "dc_gain": 1.0 / b["B"]}


def _reported(cand: Candidate, named: tuple[str, ...]) -> dict[str, float]:
    """The final model's values as the JSON reports them, keyed as its ``units`` and ``std``:
    the base net of a companion force, ``pole``, ``dc_gain``; each named effect's parameters
    as :func:`~servobench.bench.diagnose.workflow.named_parameters` gives them, other terms'
    as the model file writes them, as ``"effect.parameter"``."""
    force = companion_force(cand, named)
    out = _base_json(net_base(cand, named))
    for name, values in cand.effects.items():
        if name in named:
            params = named_parameters(name, dict(values), dict(cand.base), force)
        else:
            params = written_parameters(name, values)
        out.update({f"{name}.{k}": float(v) for k, v in params.items()})
    return out


def parameter_std(d: Diagnosis) -> dict[str, float]:
    """1-sigma of every value of the final model a fitted parameter moves (see the module
    docstring); empty when the final fit has no covariance, NaN where the data do not
    determine a parameter."""
    cov = d.steps[-1].fit.covariance
    if cov is None:
        return {}
    named = tuple(e.name for e in d.effects)

    def reported(c: Candidate) -> dict[str, float]:
        return {**_reported(c, named), **delay_of(c)}

    return candidate_std(d.final, cov, reported)


def colour_note(d: Diagnosis) -> str:
    """The note on a coloured training residual of the final fit (empty when white)."""
    cov = d.steps[-1].fit.covariance
    colour = None if cov is None else cov.colour
    return (
        colour.note("the final fit's training", by=NOISE_MODEL)
        if colour is not None and colour.coloured
        else ""
    )


def sigma_note(d: Diagnosis) -> str:
    """The note on what the 1-sigma cover where the final model does not reproduce the log to
    its noise (empty where it does, or where nothing has a sigma)."""
    if d.verdict.explained or d.steps[-1].fit.covariance is None:
        return ""
    return (
        f"the final model leaves a gap of {d.gap_after:.3g}% where the noise explains "
        f"{d.verdict.floor.percent:.3g}%: its 1-sigma allow for the sensor noise, not for what the "
        "model lacks, and its values may be off by more"
    )


def notes(d: Diagnosis) -> list[str]:
    """The diagnosis' notes, the coloured-residual note and the note on what the sigmas cover."""
    return list(d.notes) + [n for n in (colour_note(d), sigma_note(d)) if n]


def model_json(d: Diagnosis) -> dict:
    """The content of ``model.json`` (:mod:`servobench.bench.diagnose.model_file`)."""
    return _clean(
        model_record(
            d.final,
            d.data.units,
            d.gap_after,
            noise_floor_percent=d.verdict.floor.percent,
            verdict=d.verdict.verdict,
            comparison=d.data.comparison,
            source=d.data.source,
            std=record_std(d.final, d.steps[-1].fit.covariance),
        )
    )


def _rounds_json(d: Diagnosis) -> list[dict]:
    return [
        {
            "round": i,
            "reference_gap_held_out": rnd.reference_gap,
            "candidates": [
                {
                    "effects": list(t.effects),
                    "gap_held_out": t.gap_held_out,
                    "chosen": t.chosen,
                    "reason": t.reason,
                }
                for t in rnd.tried
            ],
            "not_refitted": [
                {"effect": n, "score": score, "quick_gap_held_out": gap}
                for n, score, gap in rnd.not_refitted
            ],
        }
        for i, rnd in enumerate(d.trace.rounds, 1)
    ]


def to_json(d: Diagnosis) -> dict:
    """The one JSON object ``servobench diagnose --json`` prints; the verdict comes first."""
    v = d.verdict
    std = parameter_std(d)
    out = {
        "verdict": v.verdict,
        "noise_floor_percent": v.floor.percent,
        "unexplained_signature": v.signature,
        "gap_before": d.gap_before,
        "gap_after": d.gap_after,
        "effects": [
            {
                "name": e.name,
                "parameters": dict(e.parameters),
                "evidence": e.evidence,
                "rivals": list(e.rivals),
            }
            for e in d.effects
        ],
        "base_before": _base_json(d.base_before),
        "base_after": {**_base_json(d.base), **delay_of(d.final)},
        "base_start": d.start.source,
        "sim_url": sim_url(d.final),
        "units": parameter_units(d.final, d.data.units),
        "std": std,
        "noise": {
            "sensor_percent": v.floor.sensor_percent,
            "repeat_percent": v.floor.repeat_percent,
            "unpredictable_percent": v.floor.unpredictable_percent,
            "rest_percent": v.floor.rest_percent,
            "lower_percent": v.floor.lower_percent,
            "upper_percent": v.floor.upper_percent,
            "floor_from": v.floor.source,
            "parts": [p.as_dict() for p in v.floor.parts],
        },
        "residual": {
            "places": [{"place": p.name, "held_out_share": p.share} for p in v.places],
            "spectrum": v.spectrum,
        },
        "steps": [
            {
                "added": list(s.added),
                "model": list(s.fit.candidate.names),
                "gap": s.fit.gap,
                "gap_held_out": s.fit.gap_held_out,
            }
            for s in d.steps
        ],
        "families": [f.as_dict() for f in d.families],
        "notes": notes(d),
        "comparison": d.data.comparison,
        "velocity": "derived from position" if d.data.derived else "measured",
        "findings": d.signatures.findings(),
        "tried": _rounds_json(d),
        "search_stop": d.trace.stop,
    }
    return _clean(out)


def _pm(value: float, std: float | None, digits: int = 4) -> str:
    """``value ± sigma`` (sigma to two significant digits), the value alone without one."""
    text = f"{value:.{digits}g}"
    if std is None:
        return text
    return f"{text} ± {std:.2g}" if math.isfinite(std) else f"{text} ± ?"


def _params_text(
    d: Diagnosis, name: str, params: dict, sep: str = " = ", std: dict | None = None
) -> str:
    units = parameter_units(d.final, d.data.units)
    std = parameter_std(d) if std is None else std
    parts = []
    for k, value in params.items():
        unit = units.get(f"{name}.{k}") or (units["B"] if k in ("B_pos", "B_neg") else "")
        unit = "" if unit in ("", "1") else f" {unit}"
        parts.append(f"{k}{sep}{_pm(value, std.get(f'{name}.{k}'))}{unit}")
    return ", ".join(parts)


def summary_lines(d: Diagnosis) -> list[str]:
    """What ``servobench diagnose`` prints (and the report opens with): the verdict first."""
    v = d.verdict
    lines = [v.headline()]
    f = v.floor
    bar = (f"the noise lies between {f.lower_percent:.3g}% and {f.upper_percent:.3g}%; "
           if f"{f.lower_percent:.3g}" != f"{f.upper_percent:.3g}" else "")  # fmt: skip
    lines.append(f"noise floor {f.percent:.3g}% ({bar}{f.source}); comparison: {d.data.comparison}")
    lines.append(f"velocity gap: {d.gap_before:.3g}% before, {d.gap_after:.3g}% after")
    if not d.effects:
        lines.append(f"no effect named: {d.trace.stop}")
    std = parameter_std(d)
    for i, e in enumerate(d.effects, 1):
        lines.append(f"{i}. {e.name} ({_params_text(d, e.name, e.parameters, '=', std)})")
        lines.append(f"   {e.evidence}")
    b = _base_json(d.base)
    sigma = any(std.get(k) is not None for k in _BASE_SHOWN)
    lines.append(
        "final base: "
        + ", ".join(f"{k}={_pm(float(b[k]), std.get(k))}" for k in _BASE_SHOWN)
        + (" (1-sigma)" if sigma else " (no 1-sigma: the log does not determine them)")
    )
    lines += [f"note: {f.sentence}" for f in d.families]
    lines += [f"note: {n}" for n in notes(d)]
    lines.append(f"diagnosed plant: {sim_url(d.final)}")
    return lines


def write_comparison_csv(d: Diagnosis, path: str | Path) -> Path:
    """``run,t,v_measured,v_before,v_after`` for every sample of every run."""
    path = Path(path)
    before, after = d.steps[0].fit.v_sim, d.steps[-1].fit.v_sim
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["run", "t", "v_measured", "v_before", "v_after"])
        for r, vb, va in zip(d.data.segments, before, after, strict=True):
            for row in zip(np.full(len(r.t), r.run), r.t, r.v, vb, va, strict=True):
                w.writerow([int(row[0])] + [format(float(x), ".10g") for x in row[1:]])
    return path


def write_model(d: Diagnosis, path: str | Path) -> Path:
    """``model.json`` of the diagnosed plant."""
    path = Path(path)
    path.write_text(json.dumps(model_json(d), indent=2) + "\n", encoding="utf-8")
    return path


def _model_table(d: Diagnosis) -> list[str]:
    units = parameter_units(d.final, d.data.units)
    before, after = _base_json(d.base_before), _base_json(d.base)
    before_std = _base_std(d.steps[0].fit)
    std = parameter_std(d)
    effects = "+".join(d.final.names)
    head = f"refitted with {effects}" if effects else "refitted (no effect added)"
    lines = [
        f"| parameter | base fit, before any effect | final model, {head} "
        "| 1-sigma, before | 1-sigma, final | unit |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for k in _BASE_SHOWN:
        lines.append(
            f"| {k} | {before[k]:.4g} | {after[k]:.4g} | {_sigma(before_std.get(k))} "
            f"| {_sigma(std.get(k))} | {units[k]} |"
        )
    return lines


def _sigma(std: float | None) -> str:
    """A 1-sigma to two significant digits, ``-`` when there is none."""
    return "-" if std is None else f"{std:.2g}" if math.isfinite(std) else "?"


def _base_std(fit) -> dict[str, float]:
    """1-sigma of a base-only fit's :func:`_base_json` values (empty without a covariance)."""
    if fit.covariance is None:
        return {}
    return candidate_std(fit.candidate, fit.covariance, lambda c: _base_json(c.base))


def _rounds_md(d: Diagnosis) -> list[str]:
    lines = []
    for i, rnd in enumerate(d.trace.rounds, 1):
        lines.append(f"Round {i} (current model: held-out gap {rnd.reference_gap:.3g}%):")
        lines.append("")
        for t in sorted(rnd.tried, key=lambda t: t.gap_held_out):
            mark = "**chosen**" if t.chosen else "rejected"
            lines.append(f"- {'+'.join(t.effects)}: {t.gap_held_out:.3g}%, {mark}: {t.reason}")
        if rnd.not_refitted:
            skipped = ", ".join(f"{n} ({q:.3g}%)" for n, _, q in rnd.not_refitted)
            lines.append(
                f"- not refitted (no signature in screening, and the quick simulation of their "
                f"guess did not beat the current model; held-out gap of that guess): {skipped}"
            )
        lines.append("")
    lines.append(f"The search stopped: {d.trace.stop}.")
    return lines


def write_report(d: Diagnosis, out_dir: str | Path) -> Path:
    """Write ``comparison.csv``, ``model.json``, the figures and ``report.md`` into ``out_dir``."""
    from servobench.bench.report.diagnose_figures import write_figures

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_comparison_csv(d, out / COMPARISON_FILE)
    write_model(d, out / MODEL_FILE)
    figures = write_figures(d, out)
    v = d.verdict
    lines = ["# servobench diagnose", "", f"**{v.headline()}**", ""]
    lines += [
        f"Noise floor {v.floor.percent:.3g}% (the noise between {v.floor.lower_percent:.3g}% and "
        f"{v.floor.upper_percent:.3g}%): {v.floor.source} (measurement "
        f"{v.floor.sensor_percent:.3g}%"
        + (
            f", period-to-period scatter {v.floor.repeat_percent:.3g}%"
            if v.floor.repeat_percent is not None
            else ""
        )
        + f", unpredictable part of the final residual {v.floor.unpredictable_percent:.3g}%"
        + (
            f", residual where the model holds the axis at rest {v.floor.rest_percent:.3g}%"
            if v.floor.rest_percent is not None
            else ""
        )
        + ").",
        "",
        f"Log: `{Path(d.data.source).name or 'log'}`; velocity "
        f"{'derived from position' if d.data.derived else 'measured'}; comparison: "
        f"{d.data.comparison}; base model started from {d.start.source}.",
        "",
        f"Velocity gap (NRMSE): {d.gap_before:.3g}% before, {d.gap_after:.3g}% after.",
        "",
        "## Model",
        "",
        *_model_table(d),
        "",
        "## Effects added",
        "",
    ]
    if not d.effects:
        lines.append(f"None: {d.trace.stop}.")
    std = parameter_std(d)
    for i, e in enumerate(d.effects, 1):
        text = _params_text(d, e.name, e.parameters, std=std)
        lines.append(f"{i}. **{e.name}** ({text}): {e.evidence}.")
    lines += ["", f"Diagnosed plant, to simulate or serve: `{sim_url(d.final)}`", ""]
    if d.families or notes(d):
        lines += ["## Notes", ""] + [f"- {f.sentence}" for f in d.families]
        lines += [f"- {n}" for n in notes(d)] + [""]
    lines += ["## Steps", "", "| model | gap [%] | held-out gap [%] |", "| --- | --- | --- |"]
    for s in d.steps:
        names = s.fit.candidate.names
        lines.append(
            f"| {'base' if not names else 'base + ' + ' + '.join(names)} | {s.fit.gap:.3g} | "
            f"{s.fit.gap_held_out:.3g} |"
        )
    lines += ["", "## Where the final model's residual lives", ""]
    lines += [
        "Share of the final residual each place predicts on held-out samples "
        "(the places are fitted on the training samples):",
        "",
    ]
    lines += [f"- {LABELS[p.name]}: {100 * p.share:.0f}%" for p in v.places]
    lines += ["", f"In frequency: {v.spectrum}.", "", "## Where the base model disagrees", ""]
    lines += [f"- {s}" for s in d.signatures.findings()]
    lines += ["", "## Candidates refitted", "", *_rounds_md(d), "", "## Figures", ""]
    for i, fig in enumerate(figures, 1):
        lines += [f"![Figure {i}]({fig.name})", "", f"*Figure {i}. {fig.caption}*", ""]
    path = out / REPORT_FILE
    path.write_text("\n".join(lines), encoding="utf-8")
    return path

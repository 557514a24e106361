"""``servobench program MODEL``: the values to program into the drive, from any saved model.

MODEL is any model servobench writes (``identify --json`` or ``identify --out``'s
``model.json``, ``diagnose --json`` or its ``model.json``, the ``model.json`` of
``sidbe`` and ``commission``). Without re-running a commissioning, the same
design code (:mod:`servobench.bench.commission.design`) gives the friction
feed-forward per direction, the viscous feed-forward and the velocity PI, each
in the model's units (SI where the driver converts) and in the drive's own units
where the model carries the drive's scale factors (``drive_scale``) or
``--log`` names a log whose header states them (``scale_u``, ``scale_v``).

The model programmed is a commissioning record's ``program_source`` (the
diagnosed model when its diagnosis closed the gap), a diagnosed model's base
refitted with its effects, else the file's base model; the output says which.
The PI is designed at ``--fs`` (default: the rate the model file states, the
identification rate) with the commissioning defaults (60 deg phase margin,
one cycle of delay, PI zero 4 times below the crossover).

``--format text`` (default) prints a table; ``csv`` one row per value
(``name,value,unit,drive_value,drive_unit,note``); ``json`` one object
(``model``, ``source``, ``fs``, ``values``, ``feed_forward``, ``velocity_pi``);
``toml`` an array of ``[[value]]`` tables.
"""

from __future__ import annotations

import argparse
import math

FORMATS = ("text", "csv", "json", "toml")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", metavar="MODEL", help="model file: identify/diagnose --json output, or any model.json")
    p.add_argument("--format", choices=FORMATS, default="text", help="output format (default text)")
    p.add_argument("--fs", type=float, default=None, metavar="HZ",
                   help="velocity-loop rate the PI is designed for (default: the model file's fs)")
    p.add_argument("--log", default=None, metavar="LOG",
                   help="take the drive's scale factors (scale_u, scale_v) from this log's header")
    p.add_argument("--phase-margin", type=float, default=60.0, metavar="DEG",
                   help="target phase margin of the PI (default 60)")
    p.add_argument("--delay-cycles", type=float, default=None, metavar="N",
                   help="delay beyond the zero-order hold [cycles] (default: 1 plus the model's "
                   "identified drive action delay delay_s)")
    p.add_argument("--sign-band", type=float, default=0.0, metavar="V",
                   help="reference speed below which the Coulomb feed-forward ramps in (default 0: a step)")  # fmt: skip


def run(args: argparse.Namespace) -> None:
    from servobench.analysis import program

    values = program(args.model, fs_hz=args.fs, log=args.log, phase_margin_deg=args.phase_margin,
                     delay_cycles=args.delay_cycles, sign_band=args.sign_band)  # fmt: skip
    print({"text": _text, "csv": _csv, "json": _json, "toml": _toml}[args.format](values), end="")


def _cell(value: float) -> str:
    return "" if isinstance(value, float) and math.isnan(value) else f"{value:.6g}"


def _text(values) -> str:
    head = values.to_dict()
    lines = [f"values to program from {head['model']}: {head['source']}",
             f"velocity loop at {head['fs']:g} Hz; drive units: {head['drive_units']}"]  # fmt: skip
    for v in values:
        if math.isnan(v.value):
            lines.append(f"  {v.name}: {v.note}")
            continue
        own = "" if (v.drive_unit == v.unit and v.drive_value == v.value) else f"  = {v.drive_value:.6g} {v.drive_unit}"
        lines.append(f"  {v.name}: {v.value:.6g} {v.unit}{own}" + (f"  ({v.note})" if v.note else ""))
    return "\n".join(lines) + "\n"


def _csv(values) -> str:
    import csv
    import io

    buf = io.StringIO()
    out = csv.writer(buf, lineterminator="\n")
    out.writerow(["name", "value", "unit", "drive_value", "drive_unit", "note"])
    for v in values:
        out.writerow([v.name, _cell(v.value), v.unit, _cell(v.drive_value), v.drive_unit, v.note])
    return buf.getvalue()


def _json(values) -> str:
    import json

    return json.dumps(values.to_dict(), allow_nan=False) + "\n"


def _toml(values) -> str:
    import json

    head = values.to_dict()

    def text(s: str) -> str:
        return json.dumps(s, ensure_ascii=False)  # a JSON string is a TOML basic string

    lines = [f"# servobench program: values to program from {head['model']}",
             f"# {head['source']}",
             f"model = {text(head['model'])}", f"source = {text(head['source'])}", f"fs = {head['fs']!r}",
             f"drive_units = {text(head['drive_units'])}"]  # fmt: skip
    for v in values:
        lines += ["", "[[value]]", f"name = {text(v.name)}"]
        if not math.isnan(v.value):
            lines += [f"value = {float(v.value)!r}", f"unit = {text(v.unit)}",
                      f"drive_value = {float(v.drive_value)!r}", f"drive_unit = {text(v.drive_unit)}"]  # fmt: skip
        if v.note:
            lines.append(f"note = {text(v.note)}")
    return "\n".join(lines) + "\n"

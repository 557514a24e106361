"""Read back any model servobench writes: ``identify --json``, ``model.json``, ``diagnose --json``.

Every one of them holds the base model: ``identify --json`` and the
``model.json`` of ``sidbe`` and ``commission`` at their top level (``M``,
``B``, ``coulomb_pos``, ``coulomb_neg``, optionally ``resonance`` and the
drive's action delay ``delay_s`` [s], 0 when absent), the
output of ``diagnose`` as ``base_after``. A diagnosed model also holds its
effects, a list of ``{"name": ..., "parameters": {...}}`` (or a mapping
``{name: {parameter: value}}``); parameters an effect does not declare
(``B_pos``, ``B_neg`` of ``viscous_asymmetry``, written for the reader) are
left out, and the rest are checked against the effect's declared ranges.

What the values to program need beside the model is read too, where the
file has it: the loop rate (``fs``, the identification rate of ``sidbe`` and
``identify``), the drive's scale factors (``drive_scale``, written from the
log's ``scale_u``/``scale_v``/``scale_x``), and, in a commissioning record,
the model its values were designed from (``program_source``: the diagnosed
model when the diagnosis closed the gap), which :func:`program_model` returns.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from servobench.bench.model.servo import Resonance, ServoModel
from servobench.errors import IdentificationError, UsageError, one_line
from servobench.sim_backend.physics import effects as effect_library

BASE_KEYS = ("M", "B", "coulomb_pos", "coulomb_neg")


@dataclass(frozen=True)
class SavedModel:
    """A model read from a file.

    Attributes
    ----------
    model : ServoModel
        The base model (and its series resonance, if it has one).
    effects : mapping
        ``{effect name: {parameter: value}}`` in the order they were added (diagnose).
    kind : str
        What wrote it: ``"identify"`` (also ``sidbe`` and ``commission``) or ``"diagnose"``.
    units : mapping
        The ``units`` object of the file, when it has one.
    source : str
        The file.
    fs_hz : float or None
        The identification (loop) rate the file states (``fs``) [Hz].
    drive_scale : mapping
        The file's ``drive_scale`` object (the drive's scale factors), empty when none.
    program_source : mapping
        A commissioning record's ``program_source`` (the model its values come from), else empty.
    """

    model: ServoModel
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    kind: str = "identify"
    units: Mapping[str, str] = field(default_factory=dict)
    source: str = ""
    fs_hz: float | None = None
    drive_scale: Mapping[str, Any] = field(default_factory=dict)
    program_source: Mapping[str, Any] = field(default_factory=dict)


def read_model(path: str | Path) -> SavedModel:
    """Read a model file; :class:`UsageError` naming the file and what is wrong with it."""
    where = one_line(str(path))
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UsageError(f"no such model file: {where}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise UsageError(f"cannot read model file {where}: {getattr(err, 'strerror', None) or err}") from None
    except json.JSONDecodeError as err:
        raise UsageError(f"{where} is not JSON ({err.msg}, line {err.lineno}); "
                         "give the output of identify --json or diagnose --json, or a model.json") from None  # fmt: skip
    if not isinstance(doc, dict):
        raise UsageError(f"{where} holds no JSON object")
    return model_from_json(doc, where)


def model_from_json(doc: Mapping[str, Any], where: str = "model") -> SavedModel:
    """The :class:`SavedModel` of a parsed model file."""
    kind = "diagnose" if isinstance(doc.get("base_after"), Mapping) else "identify"
    base = doc["base_after"] if kind == "diagnose" else doc
    missing = [k for k in BASE_KEYS if k not in base]
    if missing:
        raise UsageError(
            f"{where} is not a servobench model: it lacks {', '.join(missing)}; give the output "
            "of identify --json or diagnose --json, or the model.json of sidbe or commission"
        )
    values = {k: _number(base[k], k, where) for k in BASE_KEYS}
    resonance = None
    if isinstance(base.get("resonance"), Mapping):
        r = base["resonance"]
        resonance = Resonance(_number(r.get("wn_rad_s"), "resonance.wn_rad_s", where),
                              _number(r.get("zeta"), "resonance.zeta", where))  # fmt: skip
    delay = _number(base["delay_s"], "delay_s", where) if base.get("delay_s") is not None else 0.0
    try:
        model = ServoModel(**values, resonance=resonance, delay_s=delay)
    except IdentificationError as err:
        raise UsageError(f"{where}: {err}") from None
    units = doc.get("units") if isinstance(doc.get("units"), Mapping) else {}
    found = _effects(doc.get("effects", []), where)
    fs = _rate(doc)
    fs_hz = _number(fs, "fs", where) if fs is not None else None
    scale = doc.get("drive_scale") if isinstance(doc.get("drive_scale"), Mapping) else {}
    chosen = doc.get("program_source") if isinstance(doc.get("program_source"), Mapping) else {}
    return SavedModel(model, found, kind, {str(k): str(v) for k, v in units.items()}, where, fs_hz,
                      dict(scale), dict(chosen))  # fmt: skip


def program_model(saved: SavedModel) -> tuple[ServoModel, str]:
    """The model to design the values to program from, and one sentence saying which it is.

    A commissioning record's ``program_source`` (the diagnosed model when the diagnosis
    closed the gap) wins over its top level; a diagnosed model's base is the base refitted
    together with its effects; otherwise the file's base model.
    """
    chosen = saved.program_source
    if chosen and all(k in chosen for k in BASE_KEYS):
        values = {k: _number(chosen[k], f"program_source.{k}", saved.source) for k in BASE_KEYS}
        model = ServoModel(**values, resonance=saved.model.resonance, delay_s=saved.model.delay_s)
        return model, str(chosen.get("description") or f"the model the record programs ({chosen.get('model')})")
    if saved.kind == "diagnose" or saved.effects:
        named = " + ".join(saved.effects) or "no effect"
        return saved.model, f"the diagnosed model's base, refitted together with {named}"
    return saved.model, "the identified base model (linear block and Coulomb friction per direction)"


def _rate(doc: Mapping[str, Any]) -> Any:
    """The loop rate a model file states [Hz]: ``fs``, else a commissioning record's SIDBE rate or
    its PI's sample time; None when it states none."""
    if doc.get("fs") is not None:
        return doc["fs"]
    facts = doc.get("commissioning")
    sidbe = facts.get("sidbe") if isinstance(facts, Mapping) else None
    if isinstance(sidbe, Mapping) and sidbe.get("fs") is not None:
        return sidbe["fs"]
    pi = doc.get("velocity_pi")
    if isinstance(pi, Mapping) and isinstance(pi.get("sample_time_s"), (int, float)) and pi["sample_time_s"] > 0:
        return 1.0 / pi["sample_time_s"]
    return None


def _number(value: Any, key: str, where: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise UsageError(f"{where}: {key} = {value!r} is not a number") from None
    if not math.isfinite(out):
        raise UsageError(f"{where}: {key} = {value!r} is not finite")
    return out


def _effects(raw: Any, where: str) -> dict[str, dict[str, float]]:
    """``{name: parameters}`` from a list of ``{"name", "parameters"}`` or a mapping."""
    if isinstance(raw, Mapping):
        items = list(raw.items())
    elif isinstance(raw, list):
        items = []
        for e in raw:
            if not isinstance(e, Mapping) or "name" not in e:
                raise UsageError(f"{where}: an effect needs a name and its parameters, got {e!r}")
            items.append((e["name"], e.get("parameters", {})))
    else:
        raise UsageError(f"{where}: effects must be a list or an object")
    out: dict[str, dict[str, float]] = {}
    for name, params in items:
        if name not in effect_library.names():
            raise UsageError(f"{where}: unknown effect {name!r} (known: {', '.join(effect_library.names())})")
        if not isinstance(params, Mapping):
            raise UsageError(f"{where}: parameters of {name} must be an object")
        declared = {p.name for p in effect_library.spec(name).params}
        given = {k: _number(v, f"{name}.{k}", where) for k, v in params.items() if k in declared}
        out[name] = effect_library.validate(name, given)
    return out

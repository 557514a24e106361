"""Read back any model servobench writes: ``identify --json``, ``model.json``, ``diagnose --json``.

Every one of them holds the base model: ``identify --json`` and the
``model.json`` of ``sidbe`` and ``commission`` at their top level (``M``,
``B``, ``coulomb_pos``, ``coulomb_neg``, optionally ``resonance``), the
output of ``diagnose`` as ``base_after``. A diagnosed model also holds its
effects, a list of ``{"name": ..., "parameters": {...}}`` (or a mapping
``{name: {parameter: value}}``); parameters an effect does not declare
(``B_pos``, ``B_neg`` of ``viscous_asymmetry``, written for the reader) are
left out, and the rest are checked against the effect's declared ranges.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from servobench.bench.model import Resonance, ServoModel
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
    """

    model: ServoModel
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    kind: str = "identify"
    units: Mapping[str, str] = field(default_factory=dict)
    source: str = ""


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
    try:
        model = ServoModel(**values, resonance=resonance)
    except IdentificationError as err:
        raise UsageError(f"{where}: {err}") from None
    units = doc.get("units") if isinstance(doc.get("units"), Mapping) else {}
    found = _effects(doc.get("effects", []), where)
    return SavedModel(model, found, kind, {str(k): str(v) for k, v in units.items()}, where)


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

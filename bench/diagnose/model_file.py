"""``model.json`` of a diagnosis: the diagnosed plant, loadable and simulable.

``servobench diagnose LOG --out DIR`` writes ``DIR/model.json``, one JSON object:

* the keys of ``servobench identify --json`` for the base model, as refitted
  together with the effects: ``M``, ``B``, ``pole`` (-B/M [1/s]), ``dc_gain``
  (1/B), ``coulomb_pos``, ``coulomb_neg``, ``fit_percent``
  (``100 (1 - ||v - v_sim|| / ||v - mean v||)`` of the final model over the
  diagnosis' comparison, equal to ``100 - gap_percent``) and ``method``
  (``"diagnose"``);
* ``delay_s``: where a ``time_delay`` was named, its ``delay`` [s], the action
  delay as every servobench model carries it (``program`` designs the PI with
  it; ``validate`` and ``simulate`` take the effect itself); absent where none
  was named (the diagnosis states no delay, as before);
* ``effects``: ``{effect name: {parameter: value}}`` in the order they were
  added, with the library's parameter names (:mod:`servobench.sim_backend.physics.effects`,
  e.g. ``{"stribeck": {"fs": 1.25, "vs": 0.3}}``); empty when none was named;
* ``sim_url``: the same plant as a ``sim://`` URL (base keys ``M``, ``B``,
  ``fc_pos``, ``fc_neg`` and the effects' keys; noise-free -- add
  ``noise=...`` to simulate the sensor), which ``servobench serve-sim`` and
  every simulated drive accept;
* ``units``: the unit of every parameter above (base and effects, as
  ``"effect.parameter"``) and of ``u``, ``v``, ``x``, from the log's
  ``unit_u``/``unit_v``/``unit_x`` metadata;
* ``std``: the 1-sigma of every fitted parameter beside its value, keyed as
  ``units`` (base keys, ``pole`` and ``dc_gain`` propagated, ``"effect.parameter"``);
  parameters held fixed in the fit have none, those the data do not
  determine ``null`` (:mod:`servobench.bench.diagnose.sigma`);
* ``gap_percent``, ``noise_floor_percent``, ``verdict``, ``comparison`` (how
  the gap was measured) and ``source`` (the log).

The one reader of model files, :func:`servobench.bench.model.file.read_model`
(``servobench validate``), reads it back: the base keys at the top level and
``effects`` as a mapping; ``sim_url`` is for the simulated drive and
``serve-sim``, not read back.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from servobench.bench.diagnose.sigma import ParameterCovariance, candidate_std
from servobench.bench.diagnose.simulate import Candidate
from servobench.bench.model.servo import DELAY_KEY
from servobench.sim_backend.physics import effects as library
from servobench.sim_backend.physics.effects import position_friction
from servobench.units import SignalUnits

#: Base keys, as ``servobench identify --json`` names them.
BASE_KEYS = ("M", "B", "coulomb_pos", "coulomb_neg")
METHOD = "diagnose"


#: The ``sim://`` keys of the base parameters (the URL contract of
#: :mod:`servobench.sim_backend.simurl`, which this module does not import: it reaches the
#: drive layer, and the diagnosis stays clear of transports).
URL_KEYS = {"M": "M", "B": "B", "fc_pos": "coulomb_pos", "fc_neg": "coulomb_neg"}


def sim_url(cand: Candidate) -> str:
    """The ``sim://`` URL of a candidate model (noise-free; unused spline knots left out)."""
    plant = cand.plant()  # the levels as the simulator takes them
    query = {key: float(getattr(plant, name)) for key, name in URL_KEYS.items()}
    query.update(library.to_query({n: written_parameters(n, p) for n, p in cand.effects.items()}))
    return "sim://?" + "&".join(f"{k}={v:.10g}" for k, v in query.items())


def written_parameters(name: str, params: Mapping[str, float]) -> dict[str, float]:
    """An effect's parameters as written: library names, unused spline knots left out."""
    if name == "position_friction":
        return position_friction.compact(params)
    return {k: float(v) for k, v in params.items()}


def parameter_units(cand: Candidate, units: SignalUnits) -> dict[str, str]:
    """Unit of every parameter of a model: base keys, ``"effect.parameter"``, and u, v, x."""
    out = {**units.parameters(), **{k: "s" for k in delay_of(cand)}}
    for name, values in cand.effects.items():
        kept = written_parameters(name, values)
        for p in library.spec(name).params:
            if p.name in kept:
                out[f"{name}.{p.name}"] = units.effect_parameter(p.unit)
    return out


def delay_of(cand: Candidate) -> dict[str, float]:
    """``{"delay_s": the named time_delay's delay [s]}``, empty where none was named."""
    return {DELAY_KEY: float(cand.effects["time_delay"]["delay"])} if "time_delay" in cand.effects else {}


def record_values(cand: Candidate) -> dict[str, float]:
    """The parameters ``model.json`` gives, keyed as its ``units`` and ``std``: the base keys,
    ``pole``, ``dc_gain``, ``delay_s`` (where a delay was named) and ``"effect.parameter"``."""
    b = {k: float(cand.base[k]) for k in BASE_KEYS}
    out = {**b, "pole": -b["B"] / b["M"], "dc_gain": 1.0 / b["B"]}
    out.update(delay_of(cand))
    for name, values in cand.effects.items():
        out.update({f"{name}.{k}": v for k, v in written_parameters(name, values).items()})
    return out


def record_std(cand: Candidate, covariance: ParameterCovariance | None) -> dict[str, float]:
    """1-sigma of :func:`record_values` that the fitted parameters move (empty without a
    covariance)."""
    return {} if covariance is None else candidate_std(cand, covariance, record_values)


def model_record(
    cand: Candidate,
    units: SignalUnits,
    gap_percent: float,
    *,
    noise_floor_percent: float,
    verdict: str,
    comparison: str,
    source: str,
    std: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """The content of ``model.json``; see the module docstring (``std``: :func:`record_std`)."""
    b = {k: float(cand.base[k]) for k in BASE_KEYS}
    record: dict[str, Any] = {
        "M": b["M"],
        "B": b["B"],
        "pole": -b["B"] / b["M"],
        "dc_gain": 1.0 / b["B"],
        "coulomb_pos": b["coulomb_pos"],
        "coulomb_neg": b["coulomb_neg"],
        **delay_of(cand),
        "fit_percent": 100.0 - gap_percent,
        "method": METHOD,
        "effects": {n: written_parameters(n, p) for n, p in cand.effects.items()},
        "sim_url": sim_url(cand),
        "units": parameter_units(cand, units),
        "std": dict(std or {}),
        "gap_percent": gap_percent,
        "noise_floor_percent": noise_floor_percent,
        "verdict": verdict,
        "comparison": comparison,
        "source": Path(source).name,
    }
    return record

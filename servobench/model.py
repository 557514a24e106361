"""``servobench.Model``: an identified (or diagnosed) servo model, simulable, saved as ``model.json``.

Model (command units ``u``, velocity ``v``)::

    M dv/dt + B v = u(t - delay) - F_f,   F_f = +coulomb_pos (v > 0), -coulomb_neg (v < 0)

plus the effects a diagnosis named (``effects``). A :class:`Model` is read from
and written to the JSON objects servobench writes (``identify --json``, the
``model.json`` of ``identify --out``, ``sidbe``, ``diagnose --out`` and
``commission``, ``diagnose --json``) through the one reader of model files,
:func:`servobench.bench.model.file.model_from_json`; it keeps the object it was
read from (:attr:`Model.record`), so :meth:`Model.to_dict` gives back what the
CLI printed or wrote, with the model's own fields written over it.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from servobench.bench.model.servo import Resonance, ServoModel

__all__ = ["Model", "load_model"]

#: The base keys of a model file, in the order ``identify --json`` writes them.
BASE_ORDER = ("M", "B", "pole", "dc_gain", "coulomb_pos", "coulomb_neg")


def _to_json(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def plain(obj: Any, *, allow_nan: bool = True) -> Any:
    """``obj`` as the JSON it prints to, parsed back (lists for tuples, plain floats)."""
    return json.loads(json.dumps(obj, allow_nan=allow_nan, default=_to_json))


def _std(raw: Any) -> dict[str, float | None]:
    """A ``std`` object: each value a finite float, or None where unknown (null, NaN, "nan")."""
    if not isinstance(raw, Mapping):
        return {}
    out: dict[str, float | None] = {}
    for key, value in raw.items():
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = math.nan
        out[str(key)] = number if math.isfinite(number) else None
    return out


@dataclass(frozen=True)
class Model:
    """A servo model: the base plant, its uncertainties and units, and any named effects.

    Attributes
    ----------
    M : float
        Inertia or mass [command units * s^2 / position unit], > 0.
    B : float
        Viscous coefficient [command units * s / position unit], > 0.
    coulomb_pos, coulomb_neg : float
        Coulomb friction magnitude in positive / negative motion [command units], >= 0.
    std : mapping
        1-sigma uncertainty of each parameter (``M``, ``B``, ``coulomb_pos``,
        ``coulomb_neg``, ``delay_s`` ...) in its unit; None where unknown. Empty
        for a diagnosed model.
    units : mapping
        Unit of every parameter (``"M"``, ``"B"``, ..., ``"effect.parameter"``) and
        of the signals ``u``, ``v``, ``x``; empty when the log stated none.
    effects : mapping
        ``{effect name: {parameter: value}}`` in the order a diagnosis added them
        (names and parameters of :mod:`servobench.sim_backend.physics.effects`);
        empty for an identified base model.
    delay : float or None
        The drive's action delay ``delay_s`` [s] (a command acts ``delay`` after its
        logged instant); None when the model does not state one (0 is a stated 0).
    resonance : Resonance or None
        A series resonance of the linear block (``identify`` with ``resonance``).
    fs_hz : float or None
        The loop rate the model was identified at [Hz] (``fs``), when stated.
    source : str
        The file the model was read from or written to ("" otherwise); not compared.
    record : mapping
        The JSON object the model came from (the CLI's output for it); not compared.
        :meth:`to_dict` starts from it.
    details : servobench.bench.model.servo.IdentificationResult or None
        The identification behind a model :func:`~servobench.identify` has just found (its
        selection sentence, notes and timing figure, which the CLI's table prints); None
        otherwise. Internal types, which may change; not compared, not saved.
    """

    M: float
    B: float
    coulomb_pos: float
    coulomb_neg: float
    std: Mapping[str, float | None] = field(default_factory=dict)
    units: Mapping[str, str] = field(default_factory=dict)
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    delay: float | None = None
    resonance: Resonance | None = None
    fs_hz: float | None = None
    source: str = field(default="", compare=False)
    record: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)
    details: Any = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        put = object.__setattr__
        for name in ("M", "B", "coulomb_pos", "coulomb_neg"):
            put(self, name, float(getattr(self, name)))
        put(self, "delay", None if self.delay is None else float(self.delay))
        put(self, "fs_hz", None if self.fs_hz is None else float(self.fs_hz))
        put(self, "std", _std(self.std))
        put(self, "units", {str(k): str(v) for k, v in self.units.items()})
        put(self, "effects", {str(n): {str(k): float(v) for k, v in p.items()} for n, p in self.effects.items()})
        put(self, "record", plain(dict(self.record)))
        self.servo_model  # noqa: B018 -- raises IdentificationError for values no plant has

    # ---------------------------------------------------------------- derived
    @property
    def servo_model(self) -> ServoModel:
        """The base model as the identification code holds it (a ``delay`` of None as 0)."""
        return ServoModel(self.M, self.B, self.coulomb_pos, self.coulomb_neg, self.resonance,
                          0.0 if self.delay is None else self.delay)  # fmt: skip

    @property
    def pole(self) -> float:
        """Pole of the linear block, ``-B/M`` [1/s]."""
        return self.servo_model.pole

    @property
    def dc_gain(self) -> float:
        """DC gain of the linear block, ``1/B`` [velocity units per command unit]."""
        return self.servo_model.dc_gain

    @property
    def fit_percent(self) -> float | None:
        """The fit [%] the record states (identification or diagnosis), None when none."""
        value = self.record.get("fit_percent")
        return float(value) if isinstance(value, (int, float)) else None

    @property
    def method(self) -> str | None:
        """How the model was found (``"sidbe"``, ``"joint"``, ``"diagnose"``), None when unstated."""
        value = self.record.get("method")
        return str(value) if value is not None else None

    # ---------------------------------------------------------------- simulate
    def simulate(self, u: np.ndarray, fs: float, v0: float = 0.0) -> np.ndarray:
        """Noise-free velocity for the command sequence ``u``.

        Parameters
        ----------
        u : array_like, shape (n,)
            Command [command units], each value held for ``1/fs`` [s].
        fs : float
            Sample rate [Hz].
        v0 : float
            Initial velocity [velocity units] (position starts at 0).

        Returns
        -------
        ndarray, shape (n,)
            ``v[k]`` [velocity units] at ``t_k = k / fs``, before ``u[k]`` acts; ``u[k]`` acts
            from ``t_k + delay``. Without effects this is
            :meth:`servobench.bench.model.servo.ServoModel.simulate`; with effects, the
            simulator of ``diagnose`` and of ``sim://`` (the delay as its ``time_delay``).

        Raises
        ------
        UsageError
            A sample rate that is not > 0, effect parameters the simulator rejects.
        """
        if not self.effects:
            return self.servo_model.simulate(np.asarray(u, dtype=float), fs, v0).v
        from servobench.errors import UsageError
        from servobench.sim_backend.physics.coulomb import PlantParams, PlantState
        from servobench.sim_backend.physics.rich_plant import build_model

        if not (math.isfinite(fs) and fs > 0):
            raise UsageError(f"sample rate must be > 0 Hz, got {fs}")
        effects = {k: dict(v) for k, v in self.effects.items()}
        if self.delay and "time_delay" not in effects:
            effects = {"time_delay": {"delay": self.delay}, **effects}
        params = PlantParams(M=self.M, B=self.B, coulomb_pos=self.coulomb_pos,
                             coulomb_neg=self.coulomb_neg, effects=effects)  # fmt: skip
        v, _, _ = build_model(params).simulate(np.asarray(u, dtype=float), 1.0 / fs, PlantState(v0, 0.0))
        if self.resonance is not None:
            v = self.resonance.filter_velocity(v, 1.0 / fs)
        return np.asarray(v, dtype=float)

    # ---------------------------------------------------------------- JSON and files
    @classmethod
    def from_dict(cls, doc: Mapping[str, Any], source: str = "") -> Model:
        """The model of a JSON object servobench writes (see the module docstring).

        Raises
        ------
        UsageError
            Not a servobench model: base keys missing, values not numbers, unknown effects.
        """
        return cls(**_fields(doc, source or "model"), source=source, record=doc)

    def to_dict(self) -> dict[str, Any]:
        """The model's JSON object: :attr:`record` (what the CLI printed or wrote for it), with
        the fields that differ from it written over it; for a model made in Python, the keys of
        ``identify --json`` it has (``M``, ``B``, ``pole``, ``dc_gain``, ``coulomb_pos``,
        ``coulomb_neg``, ``delay_s``, ``std``, ``units``, ``effects``, ``fs``)."""
        doc = plain(self.record)
        was = _fields(doc, self.source or "model") if doc else {}
        base = doc["base_after"] if isinstance(doc.get("base_after"), dict) else doc
        keys = ("M", "B", "coulomb_pos", "coulomb_neg", "delay", "resonance")
        if any(was.get(k) != getattr(self, k) for k in keys) or not doc:
            base.update({k: getattr(self, k) for k in BASE_ORDER})
            if self.delay is None:
                base.pop("delay_s", None)
            else:
                base["delay_s"] = self.delay
            base.pop("resonance", None)
            if self.resonance is not None:
                base["resonance"] = {"wn_rad_s": self.resonance.wn_rad_s, "zeta": self.resonance.zeta}
        for key, name in (("std", "std"), ("units", "units"), ("effects", "effects"), ("fs", "fs_hz")):
            value = getattr(self, name)
            if was.get(name) != value and (value or was.get(name)):
                doc[key] = value
        return plain(doc)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write :meth:`to_dict` as ``model.json`` at ``path`` (overwritten); return the path.

        ``servobench program``, ``validate`` and :func:`load_model` read it back.
        """
        path = Path(path)
        path.write_text(json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n", encoding="utf-8")
        return path


def _fields(doc: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The :class:`Model` fields of a model file's JSON object (read by ``model_from_json``)."""
    from servobench.bench.model.file import model_from_json

    saved = model_from_json(doc, where)
    base = doc["base_after"] if saved.kind == "diagnose" else doc
    m = saved.model
    return {
        "M": m.M,
        "B": m.B,
        "coulomb_pos": m.coulomb_pos,
        "coulomb_neg": m.coulomb_neg,
        "std": _std(doc.get("std")),
        "units": dict(saved.units),
        "effects": {k: dict(v) for k, v in saved.effects.items()},
        "delay": m.delay_s if base.get("delay_s") is not None else None,
        "resonance": m.resonance,
        "fs_hz": saved.fs_hz,
    }


def saved_model(model: Model):
    """The model as :class:`servobench.bench.model.file.SavedModel` (for ``program``)."""
    from servobench.bench.model.file import model_from_json

    return model_from_json(model.to_dict(), model.source or "model")


def load_model(path: str | os.PathLike[str]) -> Model:
    """Read any model file servobench writes (``identify --json`` or ``--out``, ``diagnose
    --json`` or ``--out``, the ``model.json`` of ``sidbe`` and ``commission``).

    Parameters
    ----------
    path : path-like
        The model file; the loaded model's :attr:`Model.source`.

    Raises
    ------
    UsageError
        With the message of ``servobench validate``/``program``: no such file, not JSON,
        not a servobench model.
    """
    from servobench.bench.model.file import read_model

    saved = read_model(path)  # the CLI's reader and its messages
    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    return Model.from_dict(doc, saved.source)

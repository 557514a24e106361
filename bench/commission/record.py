"""The commissioning record: ``model.json``, ``commission.mat``, ``commission.json``.

``model.json`` holds, at its top level, exactly the keys of
``servobench identify --json`` (M, B, pole, dc_gain, coulomb_pos,
coulomb_neg, fit_percent, method, and ``units``: the unit of every
parameter), then ``std`` (1-sigma of every parameter), the friction
feed-forward, the suggested PI, the simulation check, ``program`` (the
values to program into the drive, in the log's and the drive's own units,
:mod:`servobench.bench.model.program`), ``identity`` (site, machine,
axis, operator from the config; vendor, product, firmware, serial number
from the drive) and the facts of the commissioning (drive, limits, bump
test, diagnosis). ``commission.mat`` carries the log arrays and the same numbers
for MATLAB. ``commission.json`` is written whatever happens (success,
refusal, Ctrl-C) and says how far commissioning got.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from servobench.bench.commission.closedloop import CompensationCheck
from servobench.bench.commission.config import IdentitySettings
from servobench.bench.commission.design import FrictionFeedForward, PIDesign
from servobench.bench.commission.integration import IDENTIFY_KEYS
from servobench.bench.log.io import ExperimentLog
from servobench.bench.model.program import ProgramValue
from servobench.bench.model.servo import STD_KEYS, IdentificationResult
from servobench.bench.report.summary import derived_std
from servobench.drivers.base import DriveInfo

MODEL_FILE = "model.json"
MAT_FILE = "commission.mat"
STATUS_FILE = "commission.json"


@dataclass(frozen=True)
class Design:
    """Compensation and controller suggested from the model, with their simulation check."""

    feed_forward: FrictionFeedForward
    pi: PIDesign
    check: CompensationCheck


@dataclass
class Progress:
    """How far commissioning got; mutable while the steps run, written as ``commission.json``."""

    drive_url: str
    started: str = field(default_factory=lambda: time.strftime("%Y-%m-%dT%H:%M:%S%z"))
    steps: list[str] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)
    status: str = "running"
    reason: str = ""
    #: The record's verdict once it ran to the end ("pass", "pass with remarks", "fail"); "" before.
    verdict: str = ""
    files: list[str] = field(default_factory=list)
    durations_s: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict,
            "status": self.status,
            "reason": self.reason,
            "drive": self.drive_url,
            "started": self.started,
            "steps_done": list(self.steps),
            "durations_s": dict(self.durations_s),
            "files": sorted(set(self.files)),
            **self.facts,
        }


def _clean(value: Any) -> Any:
    """JSON-safe: numpy scalars to floats, non-finite floats to strings."""
    if isinstance(value, Mapping):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, (np.floating, float)):
        value = float(value)
        return value if math.isfinite(value) else str(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, Path):
        return value.name
    return value


def identity_record(given: IdentitySettings, info: DriveInfo) -> dict[str, str]:
    """``identity`` of ``model.json``: site, machine, axis, operator from the config, then what
    the drive reports of itself (``""`` where the protocol tells nothing)."""
    return {
        **given.as_dict(),
        "transport": info.transport,
        "vendor": info.vendor,
        "product": info.product,
        "firmware": info.firmware,
        "serial_number": info.serial_number,
    }


def write_json(path: Path, data: Mapping[str, Any]) -> Path:
    path.write_text(json.dumps(_clean(data), indent=2) + "\n", encoding="utf-8")
    return path


def model_record(
    result: IdentificationResult,
    design: Design | None,
    facts: Mapping[str, Any],
    program: tuple[ProgramValue, ...] = (),
    identity: Mapping[str, str] | None = None,
    source: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The content of ``model.json``: the ``identify --json`` object, then the commissioning.

    ``source`` (``program_source``): the model the feed-forward, the PI and ``program``
    were designed from (:mod:`servobench.bench.commission.source`).
    """
    ident = result.to_json()
    record: dict[str, Any] = {key: ident[key] for key in IDENTIFY_KEYS}
    record.update({k: v for k, v in ident.items() if k not in record})
    record["std"] = {**{k: result.std.get(k, math.nan) for k in STD_KEYS}, **derived_std(result)}
    if design is not None:
        record["feed_forward"] = design.feed_forward.as_dict()
        record["velocity_pi"] = design.pi.as_dict()
        record["simulation_check"] = design.check.as_dict()
    if source is not None:
        record["program_source"] = dict(source)
    if program:
        record["program"] = [p.as_dict() for p in program]
    if identity is not None:
        record["identity"] = dict(identity)
    record["commissioning"] = dict(facts)
    return record


def write_mat(
    path: Path, log: ExperimentLog, result: IdentificationResult, design: Design | None
) -> Path:
    """``commission.mat``: ``run, t, u, v, x`` (column vectors over all runs), ``fs`` and the numbers.

    Readable back with :func:`servobench.bench.log.io.read_log` (default variable names).
    """
    from scipy.io import savemat

    runs = list(log.runs)
    data: dict[str, Any] = {
        "run": np.concatenate([np.full(len(r), r.run, dtype=float) for r in runs]),
        "t": np.concatenate([r.t for r in runs]),
        "u": np.concatenate([r.u for r in runs]),
        "fs": float(log.fs_hz),
    }
    for name in ("v", "x"):
        if all(getattr(r, name) is not None for r in runs):
            data[name] = np.concatenate([getattr(r, name) for r in runs])
    m = result.model
    for key in ("M", "B", "coulomb_pos", "coulomb_neg", "pole", "dc_gain"):
        data[key] = float(getattr(m, key))
    data["fit_percent"] = float(result.fit_percent)
    for key, value in result.std.items():
        data[f"std_{key}"] = float(value)
    if design is not None:
        for key, value in design.feed_forward.as_dict().items():
            data[f"ff_{key}"] = float(value)
        data["pi_kp"] = design.pi.kp
        data["pi_ki"] = design.pi.ki
        data["pi_Ts"] = design.pi.sample_time_s
        data["pi_delay_cycles"] = float(design.pi.delay_cycles)
    savemat(str(path), data, oned_as="column")
    return path

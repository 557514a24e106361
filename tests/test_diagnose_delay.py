"""A diagnosed model carries its action delay as every servobench model does (``delay_s``).

Issue 28: every model carries the drive's action delay ``delay_s``, and
``program`` designs with it. A diagnosis that names ``time_delay`` gives its
delay as ``delay_s`` in ``base_after`` (JSON), ``model.json`` and ``std``; one
that names none states no delay (no ``delay_s``, as before); ``program`` on the
diagnosed model sees one cycle plus the delay.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import servobench as sb
from servobench.bench.testing.hidden_effects import random_case, write_case_log

FS_HZ = 1000.0


def _diagnosed(effect: str | None, seed: int, folder: Path):
    rng = np.random.default_rng(seed)
    case = random_case(effect, rng)
    log = sb.read_log(write_case_log(case, folder / "log.csv", rng))
    return case, sb.diagnose(log, out=folder / "diagnosis")


def test_a_named_delay_is_the_model_s_delay_s_and_program_designs_with_it(tmp_path):
    case, result = _diagnosed("time_delay", 2, tmp_path)
    assert "time_delay" in result.effects
    named = result.effects["time_delay"]["delay"]
    assert named == pytest.approx(case.effects["time_delay"]["delay"], rel=0.1)
    doc = result.to_dict()
    assert doc["base_after"]["delay_s"] == named
    assert doc["std"]["delay_s"] == doc["std"]["time_delay.delay"] > 0
    assert doc["units"]["delay_s"] == "s"
    record = json.loads((tmp_path / "diagnosis" / "model.json").read_text())
    assert record["delay_s"] == named and record["std"]["delay_s"] > 0
    loaded = sb.load_model(tmp_path / "diagnosis" / "model.json")
    assert loaded.delay == named
    pi = sb.program(loaded, fs_hz=FS_HZ).velocity_pi
    assert pi.delay_cycles == pytest.approx(1.0 + named * FS_HZ)


def test_without_a_named_delay_the_diagnosis_states_none(tmp_path):
    _, result = _diagnosed("viscous_asymmetry", 1, tmp_path)
    assert "time_delay" not in result.effects
    doc = result.to_dict()
    assert "delay_s" not in doc["base_after"] and "delay_s" not in doc["std"]
    record = json.loads((tmp_path / "diagnosis" / "model.json").read_text())
    assert "delay_s" not in record and "delay_s" not in record["units"]
    assert result.model.delay is None
    pi = sb.program(sb.load_model(tmp_path / "diagnosis" / "model.json"), fs_hz=FS_HZ).velocity_pi
    assert pi.delay_cycles == pytest.approx(1.0)

"""Real data: the EMPS axis (closed loop, position only) lacks direction-dependent viscous friction.

Janot et al. found Fv+ = 166.7 and Fv- = 240.4 N s/m on this axis. The log is
closed loop (PD on position, ``loop = closed`` in its metadata), so diagnose
compares multi-step predictions of the open-loop model driven by the logged
force, restarted from the measured state every 0.5 s, with the velocity
derived from position by a zero-phase filter.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from servobench.bench.diagnose.workflow import diagnose
from servobench.bench.log.io import read_log

pytestmark = pytest.mark.slow  # the EMPS diagnosis, 18 s

EMPS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "emps" / "emps.csv"


@pytest.fixture(scope="module")
def result():
    if not EMPS.parent.is_dir():
        pytest.skip(f"EMPS data not found at {EMPS.parent} (a fresh clone without ../shared)")
    return diagnose(read_log(EMPS))


def test_emps_is_compared_by_restarted_predictions_on_derived_velocity(result):
    assert result.data.derived
    assert result.data.horizon_s == pytest.approx(0.5)


def test_emps_names_viscous_asymmetry_and_halves_the_gap(result):
    names = [e.name for e in result.effects]
    assert names[:1] == ["viscous_asymmetry"], names
    assert result.gap_after <= 0.5 * result.gap_before, (result.gap_before, result.gap_after)


def test_emps_viscous_asymmetry_has_the_published_direction_and_size(result):
    p = result.effects[0].parameters
    # Published: Fv+ = 166.7, Fv- = 240.4 N s/m (IDIM-LS on the same data).
    assert p["B_pos"] < p["B_neg"]
    assert p["B_pos"] == pytest.approx(166.7, rel=0.15)
    assert p["B_neg"] == pytest.approx(240.4, rel=0.15)


def test_emps_text_gives_one_set_of_numbers(result):
    """Issue 12: one line said ``B_pos=158.6, B_neg=231.9`` and the next ``B+ = 163.8``. Every
    figure printed is the final model's; the evidence carries only percentages."""
    import re

    from servobench.bench.report.diagnose import summary_lines

    text = "\n".join(summary_lines(result))
    B, dB = result.base["B"], result.final.effects["viscous_asymmetry"]["dB"]
    assert [float(x) for x in re.findall(r"B_pos=([-\d.e+]+)", text)] == [pytest.approx(B + dB, rel=1e-3)]
    assert [float(x) for x in re.findall(r"B_neg=([-\d.e+]+)", text)] == [pytest.approx(B - dB, rel=1e-3)]
    assert "B+" not in text and "B-" not in text
    for evidence in (e.evidence for e in result.effects):
        assert all(n.endswith("%") for n in re.findall(r"\d[\d.]*%?", evidence)), evidence
    url = dict(kv.split("=") for kv in text.splitlines()[-1].split("?", 1)[1].split("&"))
    assert float(url["B"]) == pytest.approx(B, rel=1e-9)
    assert float(url["visc_asym"]) == pytest.approx(dB, rel=1e-9)

"""The fleet's trend rules, log identity, log search and table files, without a cluster.

Drifts are checked against values worked out by hand from the rows; the
tables are read back with pyarrow's own CSV and Parquet readers, not ours.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest

from servobench.bench.fleet.sources import find_logs
from servobench.bench.fleet.table import COLUMNS, UNITS_KEY, FleetRow, write_csv, write_parquet
from servobench.bench.fleet.trend import axis_trends
from servobench.bench.log.identity import axis_of_url, log_identity, parse_time
from servobench.drivers.url import parse_drive_url
from servobench.errors import LogFormatError, UsageError

UNITS = {"M": "kg m^2", "B": "N m s/rad", "coulomb_pos": "N m", "coulomb_neg": "N m",
         "pole": "1/s", "dc_gain": "rad/(N m s)", "u": "N m", "v": "rad/s", "x": "rad"}  # fmt: skip


def row(axis: str, day: int, *, M=0.1, B=1.0, fcp=0.5, fcn=0.4, effects="", error="", units=UNITS):
    when = datetime(2026, 1, 1, tzinfo=timezone.utc) + timedelta(days=day)
    return FleetRow(
        f"{axis}/{day}.csv", axis, when.isoformat(), M, B, -B / M, 1 / B, fcp, fcn, 99.0,
        "joint", effects, math.nan, math.nan, error, units,
    )  # fmt: skip


def test_drift_is_latest_against_first_and_flags_beyond_threshold():
    rows = [row("A", 60, fcp=0.6, B=1.1), row("A", 0), row("A", 30, fcp=0.55), row("B", 0),
            row("B", 10, fcn=0.44)]  # fmt: skip
    a, b = axis_trends(rows, threshold_percent=15.0)
    assert [r.time[:10] for r in a.records] == ["2026-01-01", "2026-01-31", "2026-03-02"]
    assert a.drift["coulomb_pos"] == pytest.approx(20.0)  # 0.5 -> 0.6
    assert a.drift["B"] == pytest.approx(10.0)
    assert a.drift["pole"] == pytest.approx(-10.0)  # -10 -> -11
    assert a.drift["dc_gain"] == pytest.approx(100 * (1 / 1.1 - 1))
    assert a.flagged and len(a.reasons) == 1 and a.reasons[0].startswith("coulomb_pos +20.0 %")
    assert "0.5 -> 0.6 N m" in a.reasons[0]
    assert b.drift["coulomb_neg"] == pytest.approx(10.0) and not b.flagged and b.reasons == ()
    assert axis_trends(rows, threshold_percent=25.0)[0].flagged is False


def test_a_fall_counts_as_a_move_and_either_direction_flags():
    (t,) = axis_trends([row("A", 0), row("A", 9, fcn=0.3)])  # -25 %
    assert t.flagged and t.reasons[0].startswith("coulomb_neg -25.0 %")


def test_a_new_effect_flags_an_axis_and_an_old_one_does_not():
    (t,) = axis_trends([row("A", 0, effects="cogging"), row("A", 5, effects="cogging;stribeck")])
    assert t.flagged and t.reasons == ("effect stribeck appeared on 2026-01-06T00:00:00+00:00, "
                                       "absent on 2026-01-01T00:00:00+00:00",)  # fmt: skip
    (same,) = axis_trends([row("A", 0, effects="cogging"), row("A", 5, effects="cogging")])
    assert not same.flagged


def test_failed_rows_are_left_out_and_zero_first_values_give_no_percentage():
    rows = [row("A", 0, fcp=0.0), row("A", 3, fcp=0.2), row("A", 4, fcp=9.0, error="bad log")]
    (t,) = axis_trends(rows)
    assert len(t.records) == 2 and t.drift["coulomb_pos"] is None
    assert t.flagged and t.reasons[0].startswith("coulomb_pos rose from 0 to 0.2")
    assert json.loads(json.dumps(t.to_json()))["drift"]["coulomb_pos"] is None
    assert axis_trends([row("X", 0, error="unreadable")]) == ()


def test_changed_units_flag_the_axis():
    linear = {**UNITS, "u": "N", "v": "m/s"}
    (t,) = axis_trends([row("A", 0), row("A", 1, units=linear)])
    assert t.flagged and "units changed" in t.reasons[0]


@pytest.mark.parametrize("bad", [0.0, -5.0, math.nan, math.inf])
def test_threshold_must_be_a_positive_percentage(bad):
    with pytest.raises(UsageError, match="--threshold"):
        axis_trends([], bad)


def test_axis_of_url_keeps_the_address_only():
    cases = {
        "canopen://can0?node=2&max_u=3&watchdog=0.5": "canopen://can0?node=2",
        "modbus+tcp://127.0.0.1:5020?unit=3&map=zlac8015d&timeout=1": "modbus+tcp://127.0.0.1:5020?unit=3",
        "serial:///dev/ttyACM0?baud=115200&axis=1": "serial:///dev/ttyACM0?axis=1",
        # a simulated axis is its plant: its keys in a fixed order, without limits and pace
        "sim://?M=0.2&fc_pos=0.3&pace=fast&max_u=4": "sim://?M=0.2&fc_pos=0.3",
        "sim://?fc_pos=0.3&M=0.2": "sim://?M=0.2&fc_pos=0.3",
        "sim://?plant=press7.toml&M=0.3": "sim://?plant=press7.toml",
        "sim://?pace=fast": "sim://",
    }
    for url, axis in cases.items():
        assert axis_of_url(parse_drive_url(url)) == axis


def test_log_identity_from_metadata_else_file_name_and_mtime(tmp_path):
    log = tmp_path / "X-7.csv"
    log.write_text("t,u,v\n")
    stamp = datetime(2025, 5, 6, 7, 8, 9, tzinfo=timezone.utc).timestamp()
    os.utime(log, (stamp, stamp))
    axis, when = log_identity({}, log)
    assert axis == "X-7" and parse_time(when) == datetime(2025, 5, 6, 7, 8, 9, tzinfo=timezone.utc)
    assert log_identity({"axis": "spindle", "time": "2026-02-03T04:05:06Z"}, log) == (
        "spindle", "2026-02-03T04:05:06+00:00")  # fmt: skip
    with pytest.raises(LogFormatError, match="not ISO 8601"):
        log_identity({"time": "last Tuesday"}, log)


def test_folders_are_searched_for_logs_but_not_for_servobench_tables(tmp_path):
    (tmp_path / "run1").mkdir()
    for name in ("log.csv", "log-1.csv", "log-2.csv"):
        (tmp_path / "run1" / name).write_text("run,t,u,v,x\n")
    (tmp_path / "fleet.csv").write_text(",".join(COLUMNS) + "\n")
    (tmp_path / "comparison.csv").write_text("run,t,v_measured,v_before,v_after\n")
    (tmp_path / "bump.csv").write_text("# experiment = bump test\nrun,t,u,v,x\n")
    (tmp_path / "garbled.csv").write_text("\x00\x01 not a log\n")
    (tmp_path / "b.csv").write_text("t,u,x\n")
    found = [Path(s.name).relative_to(tmp_path).as_posix() for s in find_logs([tmp_path])]
    assert found == [
        "b.csv",
        "garbled.csv",
        "run1/log.csv",
    ]  # a garbled log is reported, not hidden
    again = find_logs([tmp_path / "run1" / "log-2.csv", tmp_path, tmp_path / "b.csv"])
    assert [Path(s.name).name for s in again] == ["log-2.csv", "b.csv", "garbled.csv", "log.csv"]
    with pytest.raises(UsageError, match="no such log file or folder"):
        find_logs([tmp_path / "missing"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(UsageError, match="no servobench log found"):
        find_logs([tmp_path / "empty"])


def test_tables_read_back_with_pyarrow_readers(tmp_path):
    rows = [
        row("A", 0),
        row("A", 1, effects="cogging;offset"),
        FleetRow("bad.csv", "bad", "", error='x, "y"'),
    ]
    rows.append(diagnosed(row("A", 2), "base + stribeck", 0.1, 1.0, 0.5, 0.4))
    write_csv(rows, tmp_path / "fleet.csv")
    write_parquet(rows, tmp_path / "fleet.parquet")
    table = pacsv.read_csv(tmp_path / "fleet.csv", convert_options=pacsv.ConvertOptions(
        column_types={c: "string" for c in ("log", "axis", "time", "method", "effects", "error", "model")},
        strings_can_be_null=False))  # fmt: skip
    pq_table = pq.read_table(tmp_path / "fleet.parquet")
    assert table.column_names == list(COLUMNS) == pq_table.column_names
    expected = [r.record() for r in rows]
    for got in (table.to_pylist(), pq_table.to_pylist()):
        assert got == expected  # floats exact: the CSV text reads back to the same doubles
    units = json.loads(pq_table.schema.metadata[UNITS_KEY])
    assert units == {"A": UNITS}


def test_nothing_outside_fleet_imports_dask_or_pyarrow():
    code = (
        "import sys\n"
        "from servobench.bench.cli import build_parser\n"
        "build_parser()\n"
        "import servobench.bench.fleet.engine, servobench.bench.fleet.page, servobench.bench.run.runner\n"
        "bad = sorted(m for m in ('dask', 'distributed', 'pyarrow') if m in sys.modules)\n"
        "assert not bad, bad\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_batches_keep_order_and_bound_their_size():
    from servobench.bench.fleet.engine import MAX_BATCH, batches
    from servobench.bench.fleet.sources import LogSource

    sources = [LogSource(f"{i}.csv", f"/x/{i}.csv") for i in range(203)]
    for workers in (1, 2, 8, 500):
        parts = batches(sources, workers)
        assert [s for part in parts for s in part] == sources
        assert all(1 <= len(p) <= MAX_BATCH for p in parts)
    assert len(batches(sources, 2)) >= 8  # several per worker: the load balances
    assert batches([], 2) == []


def test_an_incomplete_log_is_identified_but_reported(tmp_path):
    from servobench.bench.fleet.job import process_log
    from servobench.bench.fleet.sources import LogSource
    from servobench.bench.procedure.excitation import make_design
    from servobench.bench.testing.fleet_logs import write_log
    from servobench.bench.testing.synthetic import simulate_experiment
    from servobench.sim_backend.physics.plant import PlantParams

    log = simulate_experiment(PlantParams(), make_design(2.0, periods=3, period_s=1.0))
    path = write_log(log, tmp_path / "cut.csv", {"axis": "Z"})
    text = path.read_text().replace(
        "# status = complete", "# reason = drive fault 0x7500\n# status = incomplete"
    )
    path.write_text(text)
    got = process_log(LogSource("cut.csv", str(path)))
    assert got.axis == "Z" and got.coulomb_pos == pytest.approx(0.5, rel=1e-3)
    assert got.error == "incomplete log (drive fault 0x7500): the run was cut short"


def test_trend_page_puts_flagged_axes_first_with_units_and_failed_logs(tmp_path):
    import base64
    import re

    from servobench.bench.fleet.page import write_page

    rows = [row("B", 0), row("B", 9), row("A", 0), row("A", 40, fcp=0.7),
            FleetRow("bad.csv", "bad", "", error="no 'u' column")]  # fmt: skip
    trends = axis_trends(rows)
    page = write_page(rows, trends, 20.0, tmp_path).read_text()
    verdict = re.search(r'<div class="verdict (\w+)" id="verdict">([^<]*)</div>', page)
    assert verdict.groups() == ("fail", "1 axis flagged; 1 of 5 logs failed.")
    assert page.index("<h3>Axis A</h3>") < page.index("<h3>Axis B</h3>")  # flagged first
    assert "FLAGGED: coulomb_pos +40.0 %" in page and "<th>Coulomb + [N m]</th>" in page
    assert "<th>M [kg m^2]</th>" in page and "<td>no &#x27;u&#x27; column</td>" in page
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == 3  # the overview and one per axis
    assert all(base64.b64decode(i).startswith(b"\x89PNG\r\n\x1a\n") for i in images)
    calm = write_page(rows[:2], axis_trends(rows[:2]), 20.0, tmp_path).read_text()
    assert '<div class="verdict pass" id="verdict">No axis flagged.</div>' in calm


def diagnosed(row_: FleetRow, model: str, M: float, B: float, fcp: float, fcn: float) -> FleetRow:
    from dataclasses import replace

    effects = ";".join(model.split(" + ")[1:])
    return replace(row_, effects=effects, model=model, diagnosed_M=M, diagnosed_B=B,
                   diagnosed_coulomb_pos=fcp, diagnosed_coulomb_neg=fcn)  # fmt: skip


def test_drift_compares_the_diagnosed_models_and_says_when_the_structure_changed():
    """A Stribeck peak that appears biases the base fit (B -70 %, Coulomb +85 %), not the
    diagnosed model's base parameters: no drift is reported, the new structure is said."""
    first = diagnosed(row("A", 0), "base", 0.1, 1.0, 0.5, 0.4)
    biased = row("A", 1, B=0.303, fcp=0.924, fcn=0.884)  # identify's base fit of the Stribeck axis
    last = diagnosed(biased, "base + stribeck", 0.1, 1.01, 0.51, 0.4)
    (t,) = axis_trends([first, last])
    assert t.drift["B"] == pytest.approx(1.0) and t.drift["coulomb_pos"] == pytest.approx(2.0)
    assert t.values("B") == [1.0, 1.01]
    assert t.structure == ("model structure changed on 2026-01-02T00:00:00+00:00: base -> base + stribeck; "
                           "the drift compares the base parameters of the diagnosed models",)  # fmt: skip
    assert t.reasons == ("effect stribeck appeared on 2026-01-02T00:00:00+00:00, absent on "
                         "2026-01-01T00:00:00+00:00",)  # fmt: skip
    assert t.to_json()["models"] == ["base", "base + stribeck"]
    # without the diagnosis, identify's numbers are what there is
    (plain,) = axis_trends([row("A", 0), biased])
    assert plain.drift["B"] == pytest.approx(-69.7) and plain.structure == ()


def test_the_time_axis_is_in_the_natural_unit_of_its_span():
    from servobench.bench.fleet.page import _elapsed, time_unit

    assert [time_unit(s)[0] for s in (0, 59, 119, 600, 8000, 86400, 3 * 86400)] == [
        "s", "s", "s", "min", "h", "h", "days"]  # fmt: skip
    t0 = datetime(2026, 1, 1, tzinfo=timezone.utc)
    times = [t0 + timedelta(seconds=s) for s in (0, 300, 1290)]  # a fleet run in 21.5 minutes
    values, unit = _elapsed(times, t0)
    assert unit == "min" and values == pytest.approx([0, 5, 21.5])


def test_sim_logs_of_different_plants_are_different_axes(tmp_path):
    from servobench.bench.cli import main
    from servobench.bench.log.io import read_log

    for name, url in (("a", "sim://?fc_pos=0.4&pace=fast"), ("b", "sim://?fc_pos=0.6&max_u=5"),
                      ("c", "sim://?pace=fast&fc_pos=0.4")):  # fmt: skip
        assert main(["run", "--drive", url, "--out", str(tmp_path / f"{name}.csv"), "--periods", "2",
                     "--period", "0.5"]) == 0  # fmt: skip
    axes = [read_log(tmp_path / f"{n}.csv").metadata["axis"] for n in "abc"]
    assert axes == ["sim://?fc_pos=0.4", "sim://?fc_pos=0.6", "sim://?fc_pos=0.4"]

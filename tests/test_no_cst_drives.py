"""Drives without cyclic synchronous torque are identified through their own hold (issue 29, item 5).

A drive that takes a command only as the torque offset 0x60B2 of its own
cyclic synchronous position loop (``Drive.hold_only``: EtherCAT ``serve-sim
--profile no-cst``, CANopen without CST or without the target torque 0x6071,
or ``mode=csp`` on any drive) gets closed loop by default, without a travel
window: the axis and the drive's gains are learnt from a first trial under
the hold (``hold-trial.csv``), no relay probe, and the rounds run under the
hold. Where neither CST nor CSP with 0x60B2 exists, one line names what is
missing.
"""

from __future__ import annotations

import json
import re
from importlib.resources import files

import pytest

from servobench.bench.testing.ethercat_link import link_unavailable, run_on_link
from servobench.bench.testing.sidbe_run import sidbe_json

pytestmark = pytest.mark.slow  # served drives and sidbe runs

PLANT = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
TRUE = {"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
LOCKSTEP = ["--clock", "lockstep"]
SHORT = ["--periods", "2", "--period", "2"]


def _sidbe(url: str, args: list[str]) -> dict:
    """``sidbe --json`` into a fresh folder: exit code, the model, stderr, the logs' headers."""
    return sidbe_json(url, ["--no-plots", *args], timeout_s=300)


def _model(out: dict, rel: float) -> dict:
    assert out["rc"] == 0, out["stderr"]
    assert "Traceback" not in out["stderr"]
    model = json.loads(out["stdout"])
    for key, value in TRUE.items():
        assert model[key] == pytest.approx(value, rel=rel), (key, model[key])
    assert model["loop"] == "closed"
    hold = model["hold"]
    assert hold["where"] == "drive" and hold["room"] is None  # no window: unbounded
    assert hold["trial"]["log"] == "hold-trial.csv" and "gains fitted" in hold["drive_loop"]
    assert "probe" not in hold and "probe.csv" not in out["heads"]  # no relay: no free torque
    assert "# loop = closed" in out["heads"]["hold-trial.csv"]
    assert "# hold = drive" in out["heads"]["log.csv"]
    return model


# --------------------------------------------------------------------- EtherCAT
def _link() -> None:
    why = link_unavailable()
    if why is not None:  # a failure to fix (run as root, or allow user namespaces), never a skip
        pytest.fail(f"no private EtherCAT link: {why}")


def link_short(iface: str, url: str) -> dict:
    return _sidbe(url + "&pace=fast", SHORT)


def link_short_csp(iface: str, url: str) -> dict:
    return _sidbe(url + "&pace=fast&mode=csp", SHORT)


def link_default(iface: str, url: str) -> dict:
    return _sidbe(url, [])


def link_open_loop(iface: str, url: str) -> dict:
    return _sidbe(url + "&pace=fast", [*SHORT, "--loop", "open"])


def test_sidbe_on_a_no_cst_drive_runs_under_its_hold_without_a_window() -> None:
    _link()
    out = run_on_link(__file__, "link_short", PLANT, [*LOCKSTEP, "--profile", "no-cst"])
    _model(out, rel=0.01)
    assert "bit 9 clear" in out["heads"]["log.csv"]  # the command line says why: no CST


def test_mode_csp_identifies_a_drive_with_cst_through_its_hold() -> None:
    _link()
    out = run_on_link(__file__, "link_short_csp", PLANT, LOCKSTEP)
    _model(out, rel=0.01)
    assert "(mode=csp)" in out["heads"]["log.csv"]


def test_open_loop_on_a_hold_only_drive_is_refused_in_one_line() -> None:
    _link()
    out = run_on_link(__file__, "link_open_loop", PLANT, [*LOCKSTEP, "--profile", "no-cst"])
    assert out["rc"] != 0 and "Traceback" not in out["stderr"]
    error = json.loads(out["stdout"])["error"]
    assert "--loop open" in error and "own position hold" in error


def test_default_sidbe_on_a_no_cst_drive_is_within_1_percent() -> None:
    """The acceptance: default options against the served slave on its real clock."""
    _link()
    out = run_on_link(__file__, "link_default", PLANT, ["--profile", "no-cst"])
    model = _model(out, rel=0.01)
    assert model["periods"] == 4  # the default excitation
    # the verdict follows the run's timing figure, as on every served drive in the loaded suite:
    # a plain pass within its stated accuracy (a fresh-clone suite once said "pass with remarks"
    # for a model within 1 %; its figure was not kept, so it is printed here: open)
    timing = model["timing"]
    assert model["verdict"] == ("pass" if timing["within_accuracy"] else "pass with remarks"), timing
    # the DC-synchronous slave paces the hold's cycle, one exchange per SYNC0 event: the host
    # keeps no schedule that could trail it (its deadlines counted from before the enable, every
    # one of the 32 000 cycles was late, and each beat against SYNC0 waited a whole cycle)
    assert timing["late_cycles"] == 0, timing


def test_neither_cst_nor_a_torque_offset_is_one_line_naming_what_is_missing() -> None:
    from servobench.drivers.cia402 import MODE_CSP, SUPPORTED_MODE_BITS
    from servobench.drivers.ethercat.drive import EthercatDrive
    from servobench.errors import DriveConfigError

    drive = EthercatDrive("ethercat://eth0")  # not opened: the decision alone, from the objects
    csv, csp = 1 << SUPPORTED_MODE_BITS[9], 1 << SUPPORTED_MODE_BITS[MODE_CSP]
    rx, tx = [0x6040, 0x607A, 0x60B2], [0x6041, 0x6064, 0x606C, 0x6077]
    with pytest.raises(DriveConfigError, match=r"cannot be identified: no cyclic synchronous "
                       r"torque .*, and no cyclic synchronous position"):  # fmt: skip
        drive._command_mode("slave 1", csv, rx, tx)
    with pytest.raises(DriveConfigError, match=r"cannot be identified: .*lacks 0x60B2") as err:
        drive._command_mode("slave 1", csv | csp, [0x6040, 0x607A], tx)
    assert "\n" not in str(err.value)
    assert drive._command_mode("slave 1", csv | csp, rx, tx) is True  # hold-only


# ---------------------------------------------------------------------- CANopen
def _eds(tmp_path, drop: tuple[str, ...] = (), modes: str | None = None) -> str:
    """The shipped EDS without the objects ``drop``, with 0x6502 = ``modes`` if given."""
    eds = (files("servobench.drivers") / "data" / "cia402.eds").read_text()
    for index in drop:
        eds = re.sub(rf"\n\[{index}\]\n(?:[^\[\n][^\n]*\n)*", "\n", eds)
        assert f"[{index}]" not in eds
    if modes is not None:
        eds = eds.replace("DefaultValue=0x00000288", f"DefaultValue={modes}", 1)
    path = tmp_path / f"without-{'-'.join(drop) or 'nothing'}.eds"
    path.write_text(eds)
    return str(path)


@pytest.fixture
def written(monkeypatch) -> list[tuple[int, int, int]]:
    """Every SDO download and PDO write the served CANopen drive takes: (index, sub, value)."""
    from servobench.sim_backend.servers.canopen.drive import ServedCiA402Drive

    seen: list[tuple[int, int, int]] = []
    on_write = ServedCiA402Drive._on_write

    def recording(self, index, subindex, od, data):
        seen.append((index, subindex, od.decode_raw(data)))
        return on_write(self, index, subindex, od, data)

    monkeypatch.setattr(ServedCiA402Drive, "_on_write", recording)
    return seen


def _mapped(seen: list[tuple[int, int, int]]) -> set[int]:
    """Objects written into an RPDO mapping (0x1600-0x17FF, sub-indices from 1)."""
    return {v >> 16 for i, s, v in seen if 0x1600 <= i < 0x1800 and s >= 1 and v}


def _hold_run(drive) -> list[float]:
    drive.enable()
    drive.hold_position(drive.exchange(0.0)[0].position)
    return [drive.exchange(0.8)[0].applied for _ in range(300)]


def test_canopen_drive_without_target_torque_opens_hold_only(tmp_path, written) -> None:
    from servobench.bench.testing.served_canopen import served
    from servobench.drivers.registry import open_drive

    eds = _eds(tmp_path, drop=("6071",))
    with served(eds=eds) as (_device, url):
        dry = open_drive(url)
        dry.open(read_only=True)  # commission --dry-run: planned as it would be mapped
        try:
            assert 0x6071 not in dry.session.layout.rpdo_command.objects
        finally:
            dry.close()
        with open_drive(url + "&pace=fast") as drive:
            assert drive.hold_only and "no target torque 0x6071" in drive.log_metadata()["command"]
            applied = _hold_run(drive)
    assert min(applied[100:]) < 0.5  # 0x6077: the drive's loop pushes back against the offset
    assert 0x6071 not in {i for i, _, _ in written} and 0x6071 not in _mapped(written)
    assert {0x60B2, 0x607A} <= _mapped(written)


def test_canopen_mode_csp_neither_maps_nor_writes_the_target_torque(written) -> None:
    from servobench.bench.testing.served_canopen import served
    from servobench.drivers.registry import open_drive

    with served() as (_device, url), open_drive(url + "&pace=fast&mode=csp") as drive:
        assert drive.hold_only and 0x6071 not in drive.session.layout.rpdo_command.objects
        applied = _hold_run(drive)
        drive.stop()
    assert min(applied[100:]) < 0.5
    assert 0x6071 not in {i for i, _, _ in written} and 0x6071 not in _mapped(written)


def test_canopen_without_cst_or_target_torque_and_without_offset_is_one_line(tmp_path) -> None:
    from servobench.bench.testing.served_canopen import served
    from servobench.drivers.registry import open_drive
    from servobench.errors import DriveConfigError

    eds = _eds(tmp_path, drop=("6071", "60B2"))
    with served(eds=eds) as (_device, url), pytest.raises(DriveConfigError) as err:
        open_drive(url + "&pace=fast").open()
    text = str(err.value)
    assert "0x6071" in text and "0x60B2" in text and "\n" not in text, text


def test_canopen_sidbe_through_mode_csp(tmp_path) -> None:
    from servobench.bench.testing.served import ServedSim

    with ServedSim("canopen", PLANT, clock="lockstep") as served:
        out = _sidbe(served.url + "&pace=fast&pdo_timeout=1&watchdog=2&mode=csp", SHORT)
    assert served.returncode == 0, served.stderr
    _model(out, rel=0.01)

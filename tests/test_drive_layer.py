"""The Drive layer: URLs, registry, limits, lifecycle, watchdog — on the in-process sim:// drive."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from servobench.drivers.base import Drive, Feedback, Limits
from servobench.drivers.registry import available_schemes, open_drive, resolve
from servobench.drivers.url import parse_drive_url
from servobench.errors import (
    DriveConfigError,
    DriveError,
    DriveFaultError,
    DriveUnavailableError,
    LimitExceededError,
    UsageError,
)
from servobench.sim_backend.device import WATCHDOG_FAULT, PowerState, SimulatedDevice
from servobench.sim_backend.physics.plant import PlantParams, simulate


def test_url_parts():
    url = parse_drive_url("modbus+tcp://127.0.0.1:5020?unit=3&map=x")
    assert (url.scheme, url.host, url.port, dict(url.query)) == (
        "modbus+tcp",
        "127.0.0.1",
        5020,
        {"unit": "3", "map": "x"},
    )
    rtu = parse_drive_url("modbus+rtu:///dev/ttyUSB0?baud=115200")
    assert rtu.path == "/dev/ttyUSB0" and rtu.host == ""


@pytest.mark.parametrize(
    "bad",
    ["", "sim", "://x", "canopen://can0:99999", "sim://?M=1&M=2", 42],
)
def test_malformed_urls_raise_config_errors(bad):
    with pytest.raises(DriveConfigError):
        parse_drive_url(bad)


def test_unknown_scheme_and_unknown_keys():
    with pytest.raises(DriveUnavailableError, match="unknown drive scheme"):
        open_drive("profinet://eth0")
    with pytest.raises(DriveConfigError, match="Mass"):
        open_drive("sim://?Mass=1")
    with pytest.raises(DriveConfigError, match="not a number"):
        open_drive("sim://?M=heavy")


def test_registry_lists_every_transport_scheme():
    assert {"sim", "canopen", "modbus+tcp", "modbus+rtu", "serial"} <= set(available_schemes())
    assert issubclass(resolve("sim"), Drive)


def test_sim_drive_matches_the_plant_sample_by_sample():
    u = np.sign(np.sin(np.arange(800) * 0.01)) * 3.0
    expected, _ = simulate(u, 1000.0, PlantParams(M=0.2, B=2.0, coulomb_pos=0.3, coulomb_neg=0.6))
    with open_drive("sim://?M=0.2&B=2&fc_pos=0.3&fc_neg=0.6") as drive:
        drive.set_cycle(1e-3)
        drive.enable()
        got = [drive.exchange(uk)[0].velocity for uk in u]
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


def test_commands_are_clamped_to_max_u():
    with open_drive("sim://?max_u=2") as drive:
        drive.enable()
        _, applied = drive.exchange(50.0)
        assert applied == 2.0
        assert drive.command(-9.0) == -2.0
        block = drive.exchange_block(np.array([5.0, -5.0, 1.0]))
        assert block.applied.tolist() == [2.0, -2.0, 1.0]


def test_velocity_limit_stops_and_disables_the_axis():
    with open_drive("sim://?max_v=0.5") as drive:
        drive.set_cycle(1e-3)
        drive.enable()
        with pytest.raises(LimitExceededError, match="velocity"):
            for _ in range(2000):
                drive.exchange(5.0)
        assert not drive.enabled
        assert drive.device.state is PowerState.DISABLED
        assert drive.device.command == 0.0


def test_travel_limit_in_block_mode():
    with open_drive("sim://?xmax=0.01") as drive:
        drive.enable()
        with pytest.raises(LimitExceededError, match="travel"):
            drive.exchange_block(np.full(5000, 3.0))
        assert drive.device.state is PowerState.DISABLED


def test_close_stops_disables_and_is_idempotent():
    drive = open_drive("sim://")
    drive.open()
    drive.enable()
    drive.exchange(3.0)
    drive.close()
    drive.close()
    assert drive.device.state is PowerState.DISABLED and drive.device.command == 0.0
    with pytest.raises(DriveError, match="not open"):
        drive.exchange(1.0)


def test_context_manager_disables_on_exception():
    with pytest.raises(RuntimeError), open_drive("sim://") as drive:
        drive.enable()
        drive.exchange(3.0)
        raise RuntimeError("operator error")
    assert drive.device.state is PowerState.DISABLED


def test_unclosed_drive_warns():
    drive = open_drive("sim://").open()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        drive.__del__()
    assert any(issubclass(w.category, ResourceWarning) for w in caught)
    drive.close()


def test_fault_is_reported_and_reset():
    with open_drive("sim://") as drive:
        drive.enable()
        drive.device.fault(0x2310, "overcurrent")
        with pytest.raises(DriveFaultError, match="0x2310") as info:
            drive.exchange(1.0)
        assert info.value.code == 0x2310
        assert drive.fault_code() == 0x2310
        drive.reset_fault()
        assert drive.fault_code() == 0
        drive.enable()
        drive.exchange(1.0)


def test_device_watchdog_trips_when_the_host_is_silent():
    now = [0.0]
    dev = SimulatedDevice(PlantParams(), watchdog_s=0.1, clock=lambda: now[0])
    dev.enable()
    dev.exchange(2.0)
    now[0] = 0.05
    assert not dev.check_watchdog()
    now[0] = 0.2
    assert dev.check_watchdog()
    assert dev.state is PowerState.FAULT and dev.fault_code == WATCHDOG_FAULT
    assert dev.command == 0.0
    with pytest.raises(DriveFaultError):
        dev.enable()


def test_disabled_device_applies_no_torque():
    dev = SimulatedDevice(PlantParams())
    dev.set_command(5.0)
    for _ in range(100):
        s = dev.step()
    assert s.velocity == 0.0


def test_limits_validation():
    with pytest.raises(UsageError):
        Limits(max_command=0.0)
    with pytest.raises(UsageError):
        Limits(min_position=1.0, max_position=0.0)
    lim = Limits(max_command=1.0, max_velocity=2.0)
    assert lim.clamp(3.0) == 1.0 and lim.violation(2.5, 0.0) is not None
    assert lim.violation(-1.9, 0.0) is None and math.isinf(lim.max_position)


def test_base_class_demands_a_watchdog():
    class NoWatchdog(Drive):
        def _open(self): ...
        def _close(self): ...
        def _enable(self): ...
        def _disable(self): ...
        def _write_command(self, u): ...
        def _read_feedback(self):
            return Feedback(0.0, 0.0, 0.0)

    drive = NoWatchdog("custom://")
    with pytest.raises(NotImplementedError, match="watchdog"):
        drive.open()
    assert not drive.is_open


def test_every_servobench_error_message_is_one_line():
    from servobench.errors import LogFormatError

    assert str(DriveConfigError("bad key 'a\nb'\r\nin file")) == "bad key 'a b' in file"
    fault = DriveFaultError("overcurrent\nphase U", 0x2310)
    assert str(fault) == "overcurrent phase U" and fault.code == 0x2310
    assert isinstance(LogFormatError("x\u2028y"), ValueError) and str(LogFormatError("x\u2028y")) == "x y"


def test_a_third_party_drive_joins_by_entry_point(tmp_path, monkeypatch):
    (tmp_path / "thirdparty_drive.py").write_text(
        "from servobench.drivers.sim import SimDrive\n\n"
        "class BenchTwinDrive(SimDrive):\n"
        "    '''A vendor's drive, here a renamed simulated one.'''\n"
    )
    info = tmp_path / "thirdparty_drive-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: thirdparty-drive\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[servobench.drives]\nbenchtwin = thirdparty_drive:BenchTwinDrive\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "benchtwin" in available_schemes()
    with open_drive("benchtwin://?M=0.2&B=2") as drive:
        assert type(drive).__name__ == "BenchTwinDrive"
        drive.enable()
        assert drive.exchange(1.0)[1] == 1.0
    (info / "entry_points.txt").write_text("[servobench.drives]\nbroken = no_such_module:Drive\n")
    with pytest.raises(DriveUnavailableError, match="cannot be loaded"):
        open_drive("broken://")


def test_plant_from_a_toml_file_with_url_overrides(tmp_path):
    plant = tmp_path / "plant.toml"
    plant.write_text("[plant]\nM = 0.2\nB = 2.0\nfc_pos = 0.3\nfc_neg = 0.6\n")
    u = np.full(300, 3.0)
    expected, _ = simulate(u, 1000.0, PlantParams(M=0.2, B=4.0, coulomb_pos=0.3, coulomb_neg=0.6))
    with open_drive(f"sim://?plant={plant}&B=4") as drive:
        drive.set_cycle(1e-3)
        drive.enable()
        got = drive.exchange_block(u).velocity
    np.testing.assert_allclose(got, expected, atol=1e-12)
    plant.write_text("[plant]\nM = 'heavy'\n")
    with pytest.raises(DriveConfigError, match="not a number"):
        open_drive(f"sim://?plant={plant}")
    with pytest.raises(DriveConfigError, match="plant file"):
        open_drive(f"sim://?plant={tmp_path / 'missing.toml'}")


def test_device_listeners_see_every_state_change_with_its_fault_code():
    dev = SimulatedDevice(PlantParams())
    seen = []
    dev.listeners.append(lambda state, code: seen.append((state, code)))
    dev.enable()
    dev.fault(0x2310, "overcurrent")
    dev.reset_fault()
    dev.enable()
    dev.quick_stop()
    dev.disable()
    dev.disable()  # no change, no call
    assert seen == [
        (PowerState.ENABLED, 0),
        (PowerState.FAULT, 0x2310),
        (PowerState.DISABLED, 0),
        (PowerState.ENABLED, 0),
        (PowerState.QUICK_STOP, 0),
        (PowerState.DISABLED, 0),
    ]


# ------------------------------------------------------------ declared capabilities
def test_optional_capabilities_are_declared_on_the_base_with_defaults():
    for name, default in (("realtime", True), ("supports_block", False), ("supports_drive_hold", False)):
        assert getattr(Drive, name) is default, name
    with open_drive("sim://?pace=real") as real, open_drive("sim://") as fast:
        assert (real.realtime, real.supports_block) == (True, False)
        assert (fast.realtime, fast.supports_block) == (False, True)
        assert real.link_recoveries() == {} == fast.link_recoveries()


def test_a_drive_without_a_drive_side_loop_refuses_to_hold():
    with open_drive("sim://") as drive:
        drive.enable()
        with pytest.raises(DriveUnavailableError, match="host-side hold loop"):
            drive.hold_position(0.0)
        assert not drive.holding
        drive.release_hold()  # nothing to release: no error


def test_log_metadata_carries_the_known_units_only():
    with open_drive("sim://") as drive:
        meta = drive.log_metadata()
        assert {k: meta[k] for k in ("unit_u", "unit_v", "unit_x")} == {
            f"unit_{k}": v for k, v in drive.units.items()
        }
    bare = open_drive("sim://")  # not opened: units are a plain attribute
    bare.units = {"u": "N m", "v": "", "x": "rad"}
    assert bare.log_metadata() == {"unit_u": "N m", "unit_x": "rad"}


def test_feedback_applied_defaults_to_not_reported():
    fb = Feedback(0.0, 1.0, 2.0)
    assert math.isnan(fb.applied)

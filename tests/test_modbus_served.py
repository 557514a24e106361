"""ModbusDrive against the served simulated drive in this process (a real pymodbus server).

Failure paths and map variants: exception responses, drive faults, timeouts,
a lost link, write-then-read vs FC23, timestamp roll-over, the ZLAC8015D map.
"""

from __future__ import annotations

import contextlib
import socket
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.testing.served_modbus import served_modbus
from servobench.drivers.modbus.drive import ModbusDrive, exception_error
from servobench.drivers.modbus.regmap import resolve_map
from servobench.drivers.registry import open_drive
from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveFaultError,
    DriveTimeoutError,
)
from servobench.sim_backend.device import (
    GENERIC_FAULT,
    PowerState,
    SimulatedDevice,
)
from servobench.sim_backend.physics.plant import PlantParams, simulate
from servobench.sim_backend.servers.modbus.serve_modbus import parse_faults

SIM_URL = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
SIM_MAP = Path(resolve_map("servobench-sim")).read_text()


def served(
    map_name: str = "servobench-sim", transport: str = "modbus-tcp", fault: str = ""
) -> contextlib.AbstractContextManager[tuple[SimulatedDevice, str]]:
    """The simulated drive served in a thread; yields (device, URL)."""
    return served_modbus(transport, SIM_URL, map=map_name, fault=fault)


def client_map(tmp_path: Path, old: str, new: str) -> str:
    """A copy of the served map with one edit, as the client's map=."""
    assert old in SIM_MAP
    path = tmp_path / "client.toml"
    path.write_text(SIM_MAP.replace(old, new))
    return str(path)


def with_map(url: str, map_path: str) -> str:
    return url.replace("map=servobench-sim", f"map={map_path}")


# ---------------------------------------------------------------- protocol paths
@pytest.mark.parametrize("fc23", [True, False])
def test_fc23_and_write_then_read_give_the_same_cycles(tmp_path, fc23):
    u = np.where((np.arange(200) // 40) % 2 == 0, 1.2, -1.2)
    with served() as (device, url):
        if not fc23:
            url = with_map(url, client_map(tmp_path, "fc23 = true", "fc23 = false"))
        with open_drive(url + "&watchdog=0.3") as drive:
            assert drive.regmap.fc23 is fc23
            drive.set_cycle(0.002)
            assert (device.cycle_s, device.watchdog_s) == (
                0.002,
                0.3,
            )  # cycle and watchdog registers
            drive.enable()
            assert device.state is PowerState.ENABLED
            v = np.array([drive.exchange(float(uk))[0].velocity for uk in u])
        assert device.state is PowerState.DISABLED  # close() stopped and disabled it
    np.testing.assert_allclose(v, simulate(u, 500.0, PARAMS)[0], rtol=0, atol=1e-6)


def test_read_clocks_the_lock_step_drive():
    with served() as (_, url), open_drive(url) as drive:
        drive.set_cycle(0.001)
        assert [drive.read().t_s for _ in range(3)] == pytest.approx([0.0, 1e-3, 2e-3])


def test_drive_clock_unwraps_a_rolling_timestamp(tmp_path):
    # a 16-bit timestamp of 10 us rolls over every 0.65536 s: 800 cycles of 1 ms cross it;
    # it now sits in a feedback read of its own, which must still see t_k
    path = client_map(
        tmp_path,
        'format = "uint32"\nscale = 1e-6           # drive clock',
        'format = "uint16"\nscale = 1e-5           # drive clock',
    )
    with served(path) as (_, url), open_drive(url) as drive:
        drive.set_cycle(0.001)
        t = np.array([drive.exchange(0.0)[0].t_s for _ in range(800)])
    np.testing.assert_allclose(t, np.arange(800) * 1e-3, rtol=0, atol=1e-8)


def test_watchdog_fed_through_a_register(tmp_path):
    path = client_map(tmp_path, 'feed = "any_request"', 'feed = "register"')
    text = (
        Path(path).read_text()
        + '\n[registers.watchdog_feed]\naddress = 0x0004\nformat = "uint16"\n'
    )
    Path(path).write_text(text)
    with served(path) as (_, url), open_drive(url) as drive:
        drive.enable()
        for _ in range(5):
            drive.exchange(0.0)
        assert drive._read("holding", 0x0004, 1, "watchdog_feed") == [5]  # the counter written


def test_zlac8015d_map_is_self_consistent():
    # the sim served with the real drive's layout: setup write, write-then-read, a gapped feedback read
    with served("zlac8015d") as (device, url), open_drive(url + "&watchdog=0.4") as drive:
        assert not drive.regmap.fc23 and device.watchdog_s == pytest.approx(0.4)
        drive.enable()
        u = np.full(60, 1.5)  # [A] -> 1500 mA -> 1.5 command units
        rows = [drive.exchange(float(uk))[0] for uk in u]
        assert drive.info().extra["map"] == "zlac8015d"
    v_ref, x_ref = simulate(u, 1000.0, PARAMS)
    # velocity in 0.1 r/min counts (read as rad/s): half a count; position in whole encoder counts
    half_count = 0.5 * drive.regmap["velocity"].scale
    np.testing.assert_allclose([r.velocity for r in rows], v_ref, rtol=0, atol=half_count + 1e-12)
    np.testing.assert_allclose([r.position for r in rows], x_ref, rtol=0, atol=0.5)
    assert rows[-1].velocity > 0.3


# ---------------------------------------------------------------- typed errors
def test_exception_response_names_register_and_code(tmp_path):
    moved = client_map(tmp_path, "address = 0x0108", "address = 0x0300")  # product, not served
    with (
        served() as (_, url),
        open_drive(with_map(url, moved)) as drive,
        pytest.raises(
            DriveConfigError,
            match=r"read product \(0x0300\+16\).*exception 2 \(illegal data address\)",
        ),
    ):
        drive.info()


def test_unknown_control_value_is_an_illegal_value(tmp_path):
    wrong = client_map(tmp_path, "enable = [0x0001]", "enable = [0x0005]")
    with served() as (device, url), open_drive(with_map(url, wrong)) as drive:
        with pytest.raises(
            DriveConfigError, match=r"write control.*exception 3 \(illegal data value\)"
        ):
            drive.enable()
        assert device.state is PowerState.DISABLED


def test_fault_register_raises_drive_fault_error():
    with served() as (device, url), open_drive(url) as drive:
        drive.enable()
        drive.exchange(1.0)
        device.fault(GENERIC_FAULT, "injected by the test")
        with pytest.raises(DriveFaultError, match="0x1000") as err:
            drive.exchange(1.0)
        assert err.value.code == GENERIC_FAULT
        assert drive.fault_code() == GENERIC_FAULT
        with pytest.raises(DriveFaultError) as err:
            drive.enable()
        assert err.value.code == GENERIC_FAULT
        drive.reset_fault()
        drive.enable()
        assert drive.exchange(0.0)[0].fault_code == 0


def test_refused_enable_is_a_device_failure_with_the_fault_code():
    # written behind the driver's back: the server refuses (exception 4), the driver reads the fault
    with served() as (device, url), open_drive(url) as drive:
        device.fault(GENERIC_FAULT)
        with pytest.raises(DriveFaultError, match="exception 4") as err:
            drive._control(drive.regmap.control.enable)
        assert err.value.code == GENERIC_FAULT


def test_injected_faults():
    with served(fault="busy@3;fault@6;busy@7;busy@8") as (device, url), open_drive(url) as drive:
        drive.enable()
        drive.exchange(1.0)
        drive.exchange(1.0)
        t3 = drive.exchange(1.0)[0].t_s  # request 3 is answered busy, not clocked: retried once
        assert drive.retries == 1 and t3 == pytest.approx(2e-3)
        drive.exchange(1.0)
        with pytest.raises(DriveFaultError) as err:
            drive.exchange(1.0)
        assert err.value.code == GENERIC_FAULT
        assert device.plant.state.x > 0  # cycles 1, 2, 4, 5 ran
        drive.reset_fault()
        drive.enable()
        with pytest.raises(DriveTimeoutError, match=r"exception 6 \(server device busy\)"):
            drive.exchange(1.0)  # busy twice: one retry only


@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu"])
def test_injected_silence_is_a_timeout_and_the_link_recovers(transport):
    with (
        served(transport=transport, fault="silence@2") as (_, url),
        # the silence is for good: 1 s ends it, well inside the drive's watchdog
        open_drive(url + "&timeout=1&watchdog=5") as drive,
    ):
        drive.enable()
        t0 = drive.exchange(1.0)[0].t_s
        with pytest.raises(DriveTimeoutError, match="no answer"):
            drive.exchange(1.0)
        assert drive.exchange(1.0)[0].t_s == pytest.approx(t0 + 1e-3)  # not clocked


@pytest.mark.parametrize("spec", ["fault", "fault@0", "garble@3", "busy@x"])
def test_bad_fault_specs(spec):
    with pytest.raises(DriveConfigError, match="bad --fault"):
        parse_faults(spec)


def test_silent_drive_is_a_timeout():
    with socket.create_server(("127.0.0.1", 0)) as listener:  # accepts, never answers
        port = listener.getsockname()[1]
        drive = open_drive(f"modbus+tcp://127.0.0.1:{port}?unit=1&map=servobench-sim&timeout=0.1")
        with pytest.raises(DriveTimeoutError, match="no answer from unit 1"):
            drive.open()
        assert not drive.is_open


def test_refused_connection_and_lost_link():
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]
    with pytest.raises(DriveConnectionError, match="cannot connect"):
        open_drive(f"modbus+tcp://127.0.0.1:{port}?map=servobench-sim").open()
    with served() as (_, url):
        drive = open_drive(url)
        drive.open()
    with pytest.raises(DriveConnectionError, match="lost"):  # the server is gone
        drive.exchange(0.0)
    drive.close()


@pytest.mark.parametrize(
    ("code", "kind"),
    [(1, DriveConfigError), (2, DriveConfigError), (3, DriveConfigError), (4, DriveFaultError),
     (6, DriveTimeoutError), (10, DriveConnectionError), (11, DriveTimeoutError)],
)  # fmt: skip
def test_exception_codes_map_to_typed_errors(code, kind):
    err = exception_error(code, "read x", fault_code=0x2310)
    assert type(err) is kind and f"exception {code}" in str(err)
    if kind is DriveFaultError:
        assert err.code == 0x2310


# ------------------------------------------------------------------- URLs
@pytest.mark.parametrize(
    ("url", "match"),
    [
        ("modbus+tcp://127.0.0.1:502?unit=1", "needs map="),
        ("modbus+tcp://127.0.0.1:502?map=servobench-sim&baud=9600", "baud= is for modbus\\+rtu"),
        ("modbus+tcp://127.0.0.1:502?map=servobench-sim&unti=1", "unti"),
        ("modbus+tcp://127.0.0.1:502?map=nope", "unknown register map 'nope'"),
        ("modbus+tcp://127.0.0.1:502?map=servobench-sim&unit=300", "outside 0..255"),
        ("modbus+rtu://?map=servobench-sim", "needs a device path"),
        ("modbus+rtu:///dev/ttyUSB0?map=servobench-sim&parity=X", "parity"),
    ],
)
def test_bad_urls_are_config_errors(url, match):
    with pytest.raises(DriveConfigError, match=match):
        ModbusDrive(url)

"""Issue 10 §1: bring-up from the object dictionary the drive has.

The served drive has the object set of ZeroErr's eDriver (``zeroerr-edriver.eds``):
no 0x1013, 0x6007 or 0x6072, no factor group. The host must bring it up with
and without that EDS named in the URL (SDO probing), clock it by the SYNC
count, clamp on the host alone, warn about 0x6007, write 0x1006/0x60C2 in
PRE-OPERATIONAL (the served drive refuses them in OPERATIONAL), and keep
bit 30 of the PDO COB-IDs.
"""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from importlib import resources

import can
import numpy as np
import pytest

from servobench.bench.logio import read_log
from servobench.bench.testing.served import ServedSim
from servobench.bench.testing.served_canopen import SIM, served
from servobench.drivers.registry import open_drive
from servobench.errors import DriveConnectionError, DriveTimeoutError, DriveWarning
from servobench.sim_backend.device import PowerState
from servobench.sim_backend.physics.plant import PlantParams, simulate

PLANT = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
#: The served ZeroErr counts 2**19 increments per revolution (its eRob examples).
INC_PER_RAD = 2**19 / (2 * math.pi)


def square(n: int, period: int = 100, amp: float = 1.0) -> np.ndarray:
    return np.where((np.arange(n) // (period // 2)) % 2 == 0, amp, -amp)


def _open_warned(url: str):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        drive = open_drive(url).open()
    return drive, [w for w in caught if issubclass(w.category, DriveWarning)]


@pytest.mark.parametrize("eds_in_url", [True, False], ids=["eds-in-url", "sdo-probing"])
def test_zeroerr_object_set_brings_up_with_and_without_its_eds(eds_in_url: bool) -> None:
    with served(eds="zeroerr-edriver") as (device, url):
        assert "eds=" in url  # the announced URL names the EDS it serves
        host_url = url if eds_in_url else url[: url.index("&eds=")]
        drive, warned = _open_warned(host_url + "&max_u=0.6")
        try:
            assert len(warned) == 1 and "0x6007" in str(warned[0].message)
            assert "\n" not in str(warned[0].message)
            meta = drive.log_metadata()
            assert meta["object_dictionary"] == ("EDS zeroerr-edriver" if eds_in_url else
                                                 "SDO probing (types from the generic CiA 402 EDS)")  # fmt: skip
            assert meta["drive_clock"].startswith("SYNC count")
            assert meta["max_torque"].startswith("host-side clamping only")
            assert "no 0x6007" in meta["watchdog_action"]
            assert (meta["unit_u"], meta["unit_v"], meta["unit_x"]) == ("N m", "inc/s", "inc")
            info = drive.info()
            assert info.vendor == "0x5A65726F" and "0x26483052" in info.product
            assert math.isinf(device.max_command)  # the drive has no 0x6072 to set
            drive.set_cycle(
                0.0005
            )  # refused by the drive in OPERATIONAL: written in PRE-OPERATIONAL
            assert device.cycle_s == pytest.approx(0.0005)
            drive.set_cycle(0.001)
            drive.enable()
            u = square(300, amp=0.8)
            rows = [drive.exchange(uk) for uk in u]
            assert device.command == pytest.approx(-0.6)  # clamped by the host to max_u
        finally:
            drive.close()
    v_ref, x_ref = simulate(np.clip(u, -0.6, 0.6), 1000.0, PLANT)
    fb = [r[0] for r in rows]
    np.testing.assert_allclose([f.velocity for f in fb], v_ref * INC_PER_RAD, atol=0.6)
    np.testing.assert_allclose([f.position for f in fb], x_ref * INC_PER_RAD, atol=0.6)
    np.testing.assert_allclose([f.t_s for f in fb], np.arange(300) * 1e-3, atol=1e-12)
    np.testing.assert_allclose([f.applied for f in fb[1:]], np.clip(u, -0.6, 0.6)[:-1], atol=1e-3)


def test_pdo_cob_ids_keep_bit_30_and_commands_map_as_planned() -> None:
    with served() as (_, url), open_drive(url) as drive:
        node = drive.node
        # the generic EDS's TPDOs carry bit 30 (no RTR): it stays, bit 31 is cleared
        assert node.sdo[0x1800][1].raw == 0x40000182
        assert node.sdo[0x1801][1].raw == 0x40000282
        assert node.sdo[0x1802][1].raw & 0xC0000000 == 0xC0000000  # unused: invalid, bit 30 kept
        assert [node.sdo[0x1A00][s].raw for s in (0, 1, 2, 3)] == [
            3,
            0x60410010,
            0x60770010,
            0x10130020,
        ]
        assert [node.sdo[0x1600][s].raw for s in (0, 1, 2, 3)] == [
            3,
            0x60400010,
            0x60710010,
            0x60B20010,
        ]
        assert drive.log_metadata()["drive_clock"].startswith("0x1013")


def test_cycle_objects_are_written_in_pre_operational(tmp_path) -> None:
    path = tmp_path / "bus.log"
    with served() as (device, url), open_drive(url) as drive:
        drive.record_traffic(str(path))
        drive.set_cycle(0.0005)
        assert device.cycle_s == pytest.approx(0.0005)
        drive.set_cycle(0.0005)  # unchanged: no second round trip through PRE-OPERATIONAL
    frames = [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(path)) if not m.is_rx]
    nmt = [i for i, f in enumerate(frames) if f[0] == 0x000]
    assert [frames[i][1] for i in nmt[:2]] == [b"\x80\x02", b"\x01\x02"]  # pre-op, then start
    between = frames[nmt[0] : nmt[1]]
    assert (0x602, bytes.fromhex("23061000F4010000")) in between  # 0x1006 = 500 µs
    assert (0x602, bytes.fromhex("2FC2600105000000")) in between  # 0x60C2:1 = 5
    assert (0x602, bytes.fromhex("2FC26002FC000000")) in between  # 0x60C2:2 = -4
    assert len(nmt) == 3  # the third: pre-operational at close


def test_enabled_drive_refuses_a_new_cycle() -> None:
    with served() as (device, url), open_drive(url) as drive:
        drive.enable()
        with pytest.raises(ValueError, match="before enabling"):
            drive.set_cycle(0.002)
        assert device.state is PowerState.ENABLED


def _server(behaviour: str) -> tuple[socket.socket, threading.Event]:
    """A TCP server on a free port that is no socketcand server."""
    listener = socket.create_server(("127.0.0.1", 0))
    done = threading.Event()

    def serve() -> None:
        conn, _ = listener.accept()
        if behaviour == "http":
            conn.sendall(b"HTTP/1.0 400 Bad Request\r\n\r\n<html>no</html>")
        done.wait(5)
        conn.close()

    threading.Thread(target=serve, daemon=True).start()
    return listener, done


@pytest.mark.parametrize(
    ("behaviour", "error", "match"),
    [
        ("silent", DriveTimeoutError, r"is no socketcand server: no '< hi >' within 1.0 s"),
        ("http", DriveConnectionError, r"answered '<html>' where socketcand says '< hi >'"),
    ],
)
def test_a_port_that_is_no_socketcand_server_fails_fast(behaviour, error, match) -> None:
    listener, done = _server(behaviour)
    port = listener.getsockname()[1]
    try:
        t0 = time.monotonic()
        with pytest.raises(error, match=match) as err:
            open_drive(
                f"canopen://vcan0?interface=socketcand&host=127.0.0.1&port={port}&node=2"
            ).open()
        assert time.monotonic() - t0 < 3.0
        assert "\n" not in str(err.value)
    finally:
        done.set()
        listener.close()


def test_the_cli_says_so_in_one_line(tmp_path) -> None:
    listener, done = _server("silent")
    port = listener.getsockname()[1]
    try:
        out = subprocess.run(
            [sys.executable, "-m", "servobench", "run", "--drive",
             f"canopen://vcan0?interface=socketcand&host=127.0.0.1&port={port}&node=2",
             "--out", str(tmp_path / "log.csv")],
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip
    finally:
        done.set()
        listener.close()
    assert out.returncode == 1
    assert out.stderr.count("\n") == 1 and "is no socketcand server" in out.stderr


def test_a_closed_port_is_a_connection_error() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    listener.close()
    with pytest.raises(DriveConnectionError, match="cannot reach the socketcand server"):
        open_drive(f"canopen://vcan0?interface=socketcand&host=127.0.0.1&port={port}&node=2").open()


#: A short excitation (as in test_transports_e2e): 4 s period at 50 Hz.
SIDBE_ARGS = ["--fs", "50", "--periods", "3", "--freqs", "1,2,3,5,8,13", "--amplitude", "3"]


@pytest.fixture(scope="module")
def served_zeroerr() -> Iterator[ServedSim]:
    eds = str(resources.files("servobench.drivers").joinpath("data/zeroerr-edriver.eds"))
    with ServedSim("canopen", SIM, ["--eds", eds], clock="lockstep") as sim:
        yield sim
    assert sim.returncode == 0, sim.stderr


@pytest.mark.parametrize("eds_in_url", [True, False], ids=["printed-url", "url-without-eds"])
def test_sidbe_through_serve_sim_eds(served_zeroerr: ServedSim, eds_in_url: bool, tmp_path) -> None:
    url = served_zeroerr.url
    assert "&eds=/" in url  # the file, absolute: the printed URL works from anywhere
    if not eds_in_url:
        url = url[: url.index("&eds=")]
    out = subprocess.run(
        [sys.executable, "-m", "servobench", "sidbe", "--drive", url + "&pace=fast", "--json",
         "--out", str(tmp_path / "run"), "--no-plots", *SIDBE_ARGS],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    warning = [line for line in out.stderr.splitlines() if line.startswith("servobench: warning:")]
    assert len(warning) == 1 and "no abort connection option 0x6007" in warning[0]
    model = json.loads(out.stdout)
    assert model["pole"] == pytest.approx(-10.0, rel=0.01)
    assert model["dc_gain"] == pytest.approx(INC_PER_RAD, rel=0.01)  # inc/s per N m: no 0x608F
    meta = read_log(tmp_path / "run" / "log.csv").metadata
    assert (meta["unit_u"], meta["unit_v"], meta["unit_x"]) == ("N m", "inc/s", "inc")
    assert meta["drive_clock"].startswith("SYNC count")

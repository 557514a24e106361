"""CANopen402Drive against the served CiA 402 drive, in-process over the socketcand hub.

The served drive runs in a thread (so the tests can look at the simulated
device), on the real hub over TCP; every frame goes through python-can's
socketcand client and canopen, as across processes.
"""

from __future__ import annotations

import time

import can
import canopen
import numpy as np
import pytest

from servobench.bench.testing.served_canopen import served, station
from servobench.drivers.canopen.drive import CANopen402Drive
from servobench.drivers.registry import open_drive
from servobench.drivers.url import parse_drive_url
from servobench.errors import (
    DriveConfigError,
    DriveFaultError,
    DriveTimeoutError,
    StateTransitionError,
)
from servobench.sim_backend.device import PowerState
from servobench.sim_backend.physics.plant import PlantParams, simulate
from servobench.sim_backend.servers.canopen import serve_canopen


def square(n: int, period: int = 100, amp: float = 1.0) -> np.ndarray:
    return np.where((np.arange(n) // (period // 2)) % 2 == 0, amp, -amp)


def test_open_reports_identity_and_sets_up_cycle() -> None:
    with served() as (device, url), open_drive(url) as drive:
        node = drive.node  # the driver's own canopen RemoteNode, for raw SDO checks
        info = drive.info()
        assert info.transport == "canopen"
        assert info.state == "SWITCH ON DISABLED"
        assert "servobench CiA 402 drive" in info.product
        assert info.firmware == "0.1.0"
        assert info.extra["mode"] == 10
        drive.set_cycle(0.0005)
        assert device.cycle_s == pytest.approx(0.0005)
        assert node.sdo[0x1006].raw == 500
        assert (node.sdo[0x60C2][1].raw, node.sdo[0x60C2][2].raw) == (5, -4)
        assert node.sdo[0x1016][1].raw == (127 << 16) | 500  # host node 127, 0.5 s default
        assert node.sdo[0x6007].raw == 1  # abort connection: fault


def test_square_wave_matches_the_plant() -> None:
    u = square(400)
    with served() as (_, url), open_drive(url) as drive:
        drive.set_cycle(0.001)
        drive.enable()
        rows = [drive.exchange(uk)[0] for uk in u]
    v_ref, x_ref = simulate(u, 1000.0, PlantParams(M=0.1, B=1, coulomb_pos=0.5, coulomb_neg=0.4))
    np.testing.assert_allclose([r.velocity for r in rows], v_ref, atol=1e-6)
    np.testing.assert_allclose([r.position for r in rows], x_ref, atol=1e-6)
    np.testing.assert_allclose([r.t_s for r in rows], np.arange(400) * 1e-3, atol=1e-6)


def test_quick_stop_and_re_enable() -> None:
    with served() as (device, url), open_drive(url) as drive:
        drive.enable()
        for _ in range(50):
            drive.exchange(1.0)
        assert device.state is PowerState.ENABLED and device.command == 1.0
        drive.stop()
        assert device.state is PowerState.QUICK_STOP and device.command == 0.0
        assert drive.info().state == "QUICK STOP ACTIVE"
        fb, _ = drive.exchange(1.0)  # allowed, but no torque in quick stop
        assert device.command == 0.0
        drive.enable()  # transition 16
        assert drive.info().state == "OPERATION ENABLED"
        drive.exchange(0.7)
        assert device.command == pytest.approx(0.7)
        drive.disable()
        assert device.state is PowerState.DISABLED
        assert drive.info().state == "SWITCH ON DISABLED"


def test_fault_raises_with_its_code_and_resets() -> None:
    with served() as (device, url), open_drive(url) as drive:
        drive.enable()
        drive.exchange(0.5)
        device.fault(0x2310, "overcurrent")
        with pytest.raises(DriveFaultError, match="0x2310") as err:
            drive.exchange(0.5)
        assert err.value.code == 0x2310
        assert [e.code for e in drive.node.emcy.log] == [0x2310]  # the EMCY came with the fault
        assert drive.fault_code() == 0x2310
        with pytest.raises(DriveFaultError):
            drive.enable()
        drive.reset_fault()
        assert drive.fault_code() == 0
        assert drive.info().state == "SWITCH ON DISABLED"
        drive.enable()
        drive.exchange(0.2)
        assert device.state is PowerState.ENABLED


def test_host_heartbeat_keeps_an_idle_drive_enabled() -> None:
    with served() as (device, url), open_drive(url + "&watchdog=0.5") as drive:
        drive.enable()
        time.sleep(1.5)  # no exchange, three consumer times: only heartbeats feed the consumer
        assert device.state is PowerState.ENABLED
        drive.exchange(0.0)


def test_leaving_operational_quick_stops_and_exchange_times_out() -> None:
    with (
        served() as (device, url),
        open_drive(url + "&pdo_timeout=1") as drive,  # no TPDO at all once it is timed out
        station(url) as node,
    ):
        drive.enable()
        drive.exchange(1.0)
        node.nmt.send_command(0x80)  # someone else sends the drive to PRE-OPERATIONAL
        deadline = time.monotonic() + 5.0  # the NMT command crosses the hub: late under load
        while device.state is not PowerState.QUICK_STOP and time.monotonic() < deadline:
            time.sleep(0.01)
        assert device.state is PowerState.QUICK_STOP
        with pytest.raises(DriveTimeoutError, match="no TPDO"):
            drive.exchange(1.0)


def test_a_host_stopped_past_the_tpdo_deadline_takes_the_tpdos_already_there() -> None:
    """A host stopped past the TPDO wait's deadline (a hypervisor's pause, SIGSTOP under load)
    wakes its waiting thread and the receiving one at once; the waiting one may look first and
    find nothing though the drive answered. Here its wait reports the deadline passed once while
    the receiver hands the TPDOs over: the cycle takes them (a benchmark's host stopped 30-150 ms
    now and then had stopped a served run with "no TPDO within 100 ms"). A drive that does not
    answer still times out (the tests above)."""
    import threading

    class LateLook(threading.Event):
        """The first wait after arming: as the deadline passed before the receiver ran."""

        armed = False

        def wait(self, timeout=None):
            got = super().wait(timeout)
            if LateLook.armed:
                LateLook.armed = False
                return False
            return got

    with served() as (_, url), open_drive(url) as drive:
        drive.enable()
        drive.exchange(0.0)
        io = drive.session.io
        io._rx_event = LateLook()
        LateLook.armed = True
        fb, _ = drive.exchange(0.1)
        assert not LateLook.armed  # the late look happened, and the cycle went on
        assert fb.t_s > 0


def test_drive_clamps_to_max_torque() -> None:
    with served() as (device, url), open_drive(url + "&max_u=0.5") as drive:
        node = drive.node
        assert node.sdo[0x6072].raw == 500
        assert device.max_command == pytest.approx(0.5)
        node.sdo[0x6072].raw = 300
        drive.enable()
        drive.exchange(0.5)
        assert device.command == pytest.approx(0.3)
        drive.exchange(0.5)
        assert drive.torque_actual == pytest.approx(0.3)


def test_node_that_does_not_answer_times_out() -> None:
    with served() as (_, url):
        drive = open_drive(url.replace("node=2", "node=9") + "&sdo_timeout=0.05")
        with pytest.raises(DriveTimeoutError, match="node 9 did not answer SDO"):
            drive.open()
        assert not drive.is_open


def test_rejected_mode_switch_is_a_clear_error() -> None:
    with served(fault="reject_mode=10") as (_, url):
        with pytest.raises(DriveConfigError, match=r"0x6060:0 = 10.*refused.*0x06090030"):
            open_drive(url).open()
        with open_drive(url + "&mode=pt") as drive:  # profile torque is still there
            assert drive.info().extra["mode"] == 4


def test_mode_that_does_not_show_in_0x6061_is_a_clear_error() -> None:
    with (
        served(fault="ignore_mode=10") as (_, url),
        pytest.raises(StateTransitionError, match="did not switch to mode 10"),
    ):
        open_drive(url).open()


def test_served_drive_enforces_the_pdo_mapping_procedure() -> None:
    with served() as (_, url), station(url) as node:
        with pytest.raises(canopen.SdoAbortedError) as err:
            node.sdo[0x1A00][1].raw = 0x60640020  # TPDO1 is valid: its map is locked
        assert err.value.code == 0x06040043
        node.sdo[0x1800][1].raw = 0x80000182
        node.sdo[0x1A00][0].raw = 0
        with pytest.raises(canopen.SdoAbortedError) as err:
            node.sdo[0x1A00][1].raw = 0x60760020  # rated torque is not mappable
        assert err.value.code == 0x06040041
        for sub, entry in enumerate([0x60640020, 0x606C0020, 0x60410010], start=1):
            node.sdo[0x1A00][sub].raw = entry
        with pytest.raises(canopen.SdoAbortedError) as err:
            node.sdo[0x1A00][0].raw = 3  # 80 bits > 64
        assert err.value.code == 0x06040042


def test_record_traffic_writes_both_directions(tmp_path) -> None:
    path = tmp_path / "bus.log"
    with served() as (_, url), open_drive(url) as drive:
        drive.record_traffic(str(path))
        drive.enable()
        for _ in range(2000):  # sender and notifier threads write concurrently
            drive.exchange(0.1)
    msgs = list(can.LogReader(str(path)))  # every line parses: nothing interleaved
    ids = {msg.arbitration_id for msg in msgs}
    assert {0x202, 0x080, 0x182, 0x282, 0x602, 0x582} <= ids
    syncs = [m for m in msgs if m.arbitration_id == 0x080]
    assert len(syncs) >= 2000
    assert all(not m.is_rx and m.timestamp > 0 for m in syncs)  # sent, stamped at send
    assert all(m.is_rx for m in msgs if m.arbitration_id in (0x182, 0x282))


def test_virtual_bus_in_process() -> None:
    u = square(60, period=20)
    with served(can="virtual:servobench-test") as (_, url):
        assert url.startswith("canopen://servobench-test?interface=virtual&node=2")
        with open_drive(url) as drive:
            drive.enable()
            rows = [drive.exchange(uk)[0].velocity for uk in u]
    v_ref, _ = simulate(u, 1000.0, PlantParams(M=0.1, B=1, coulomb_pos=0.5, coulomb_neg=0.4))
    np.testing.assert_allclose(rows, v_ref, atol=1e-6)


@pytest.mark.parametrize(
    ("url", "match"),
    [
        ("canopen://can0?interface=socketcan&node=2&speed=1", "speed"),
        ("canopen://can0?interface=socketcan", "node=1..127"),
        ("canopen://can0?interface=socketcan&node=128", "node=1..127"),
        ("canopen://vcan0?interface=socketcand&node=2", "host= and port="),
        ("canopen://can0?interface=socketcan&node=2&host=h&port=1", "socketcand only"),
        ("canopen://can0?node=2&mode=foo", "mode must be"),
        ("canopen://can0?node=2&host_node=2", "host_node"),
        ("canopen://?node=2", "needs a channel"),
    ],
)
def test_bad_urls_are_refused(url: str, match: str) -> None:
    with pytest.raises(DriveConfigError, match=match):
        CANopen402Drive(url)


@pytest.mark.parametrize(
    ("link", "kwargs", "url"),
    [
        ("socketcand", None, None),
        (
            "socketcan:can0",
            {"interface": "socketcan", "channel": "can0"},
            "canopen://can0?interface=socketcan&node=3",
        ),
        (
            "socketcand://127.0.0.1:29536",
            {
                "interface": "socketcand",
                "channel": "vcan0",
                "host": "127.0.0.1",
                "port": 29536,
                "tcp_tune": True,
            },
            "canopen://vcan0?interface=socketcand&host=127.0.0.1&port=29536&node=3",
        ),
        (
            "slcan:/dev/ttyACM0",
            {"interface": "slcan", "channel": "/dev/ttyACM0"},
            "canopen://?interface=slcan&channel=%2Fdev%2FttyACM0&node=3",
        ),
    ],
)
def test_link_options_and_announced_urls(link: str, kwargs: dict | None, url: str | None) -> None:
    assert serve_canopen.link_bus_kwargs(link) == kwargs
    if kwargs is not None:
        built = serve_canopen.drive_url(
            kwargs["interface"], kwargs["channel"], 3, kwargs.get("host"), kwargs.get("port")
        )
        assert built == url
        assert "scale" not in built  # the drive's factor group tells the units
        drive = open_drive(built)  # the driver accepts what the server announces
        assert (drive.interface, drive.channel, drive.node_id) == (
            kwargs["interface"],
            kwargs["channel"],
            3,
        )


@pytest.mark.parametrize("link", ["bogus", "socketcand://nohost", ":can0"])
def test_bad_links_are_refused(link: str) -> None:
    with pytest.raises(DriveConfigError):
        serve_canopen.link_bus_kwargs(link)


def test_second_served_drive_joins_the_hub() -> None:
    with served() as (dev2, url2):
        q = parse_drive_url(url2)
        join = f"socketcand://{q.get_str('host')}:{q.get_int('port')}"
        with served(can=join, node="3") as (dev3, url3):
            assert url3 == url2.replace("node=2", "node=3")
            with open_drive(url2) as drive2, open_drive(url3) as drive3:
                assert drive2.info().state == drive3.info().state == "SWITCH ON DISABLED"
                drive3.set_cycle(0.001)
                drive3.enable()
                u = square(60, period=20)
                rows = [drive3.exchange(uk)[0].velocity for uk in u]
            v_ref, _ = simulate(u, 1000.0, PlantParams(M=0.1, B=1, coulomb_pos=0.5, coulomb_neg=0.4))
            np.testing.assert_allclose(rows, v_ref, atol=1e-6)
            assert dev2.state is PowerState.DISABLED  # node 2 was not touched


def test_injected_fault_at_a_sync() -> None:
    with served(fault="fault@20") as (device, url), open_drive(url) as drive:
        drive.enable()
        for _ in range(19):
            drive.exchange(0.6)
        with pytest.raises(DriveFaultError, match="0x1000") as err:
            drive.exchange(0.6)
        assert err.value.code == 0x1000
        assert device.command == 0.0


def test_silent_sync_times_out_then_the_cycle_recovers() -> None:
    with served(fault="silence@5") as (_, url), open_drive(url + "&pdo_timeout=0.05") as drive:
        drive.enable()
        t = [drive.exchange(0.0)[0].t_s for _ in range(4)]
        with pytest.raises(DriveTimeoutError, match="no TPDO"):
            drive.exchange(0.0)
        t.append(drive.exchange(0.0)[0].t_s)
        assert t == pytest.approx([0.0, 0.001, 0.002, 0.003, 0.005])  # SYNC 5 clocked, unreported


def test_nmt_reset_node_reboots_the_served_drive() -> None:
    with served() as (device, url), open_drive(url) as drive, station(url) as node:
        drive.enable()
        drive.exchange(0.5)
        seen: list[int] = []
        node.nmt.add_heartbeat_callback(seen.append)
        node.nmt.send_command(0x81)  # reset node
        deadline = time.monotonic() + 1.0
        while 0 not in seen and time.monotonic() < deadline:  # 0: the boot-up message
            time.sleep(0.005)
        assert 0 in seen
        assert device.state is PowerState.DISABLED
        assert drive.node.sdo[0x1A00][1].raw == 0x60410010  # mapping back to the EDS default
        assert drive.info().state == "SWITCH ON DISABLED"

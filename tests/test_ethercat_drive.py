"""servobench's ``ethercat://`` drive (the master, on pysoem) against the served EtherCAT slave.

Each test runs a ``link_*`` function of this file in a child process with a
private veth link (:mod:`servobench.bench.testing.ethercat_link`): the drive
through the registry as a user opens it; ``servobench sidbe`` open loop
within 1 % of the plant and closed loop on a limited-travel axis through the
drive's own CSP loop (without the DC time stamp, and with a drive tick inside the
SYNC0 cycle: ``tests/test_drive_clock_served.py``); the CiA 402 hold; the SM watchdog armed at open,
stopping the axis when the host dies, disarmed at close; late frames counted
and bounded. Without pysoem the URL says in one line what to install.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from servobench.bench.testing.ethercat_link import link_unavailable, run_on_link
from servobench.bench.testing.sidbe_run import sidbe_json
from servobench.sim_backend.physics.plant import Plant, PlantParams, simulate

pytestmark = pytest.mark.slow  # a default sidbe (32 s at 1 kHz) and a closed-loop one: 2 min

PLANT = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
NOISY = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4&noise=0.01&seed=2"
#: serve-sim for the tests that compare exactly with the offline plant (the others run real).
LOCKSTEP = ["--clock", "lockstep"]
STREAMING_HOST = """
import sys
from servobench.drivers.registry import open_drive
drive = open_drive(sys.argv[1]).open()
drive.set_cycle(0.001)
drive.enable()
for _ in range(300):
    drive.exchange(1.0)
print("streaming", flush=True)
while True:
    drive.exchange(1.0)
"""


def _link_tests():
    why = link_unavailable()
    if why is not None:  # a failure to fix (run as root, or allow user namespaces), never a skip
        pytest.fail(f"no private EtherCAT link: {why}")


def _sidbe(url: str, args: list[str]) -> dict:
    return sidbe_json(url, args, timeout_s=300)


# ------------------------------------------------------------ link functions
def link_cycles(iface: str, url: str) -> dict:
    import pysoem

    from servobench.drivers.registry import open_drive

    out: dict = {"url": url}
    with open_drive(url + "&watchdog=0.3") as drive:
        drive.set_cycle(0.001)
        info = drive.info()
        out["info"] = {"vendor": info.vendor, "product": info.product, "state": info.state,
                       "units": dict(info.units), "al": info.extra["al_state"]}  # fmt: skip
        out["meta"] = drive.log_metadata()
        out["clock"] = drive.drive_clock
        # a host silent beyond the watchdog before enabling (a stall, a slow import): the SM
        # watchdog takes the slave to SAFE-OP, and the enable brings it back to OP
        drive.bus.keep_alive = False
        time.sleep(0.45)
        out["al_silent"] = list(drive.bus.read_state())
        drive.bus.keep_alive = True
        drive.enable()
        out["remarks"] = list(drive.remarks)
        u = np.where((np.arange(1000) // 250) % 2 == 0, 0.8, -0.8)
        rows = [drive.exchange(uk) for uk in u]
        out["v"] = [r[0].velocity for r in rows]
        out["x"] = [r[0].position for r in rows]
        out["t"] = [r[0].t_s for r in rows]
        out["applied"] = [r[0].applied for r in rows]
        out["u"] = [r[1] for r in rows]
        # the hold: the drive's own loop at x_ref, the host's command as the torque offset
        x_ref = rows[-1][0].position + 0.02
        out["hold_supported"] = drive.supports_drive_hold
        drive.hold_position(x_ref)
        held = [drive.exchange(0.0)[0] for _ in range(2000)]
        out["x_ref"] = x_ref
        out["held_x"] = [f.position for f in held[-200:]]
        out["held_applied"] = [f.applied for f in held[-200:]]
        drive.release_hold()
        drive.disable()
        out["recoveries"] = dict(drive.link_recoveries())
    # after close: the SM watchdog is disarmed (0x0420 = 0) and the slave back in INIT
    master = pysoem.Master()
    master.open(iface)
    try:
        master.config_init()
        out["wd_after_close"] = int.from_bytes(master.slaves[0]._fprd(0x0420, 2), "little")
    finally:
        master.close()
    return out


def link_sidbe_open(iface: str, url: str) -> dict:
    """A default ``sidbe`` (1 kHz, paced in real time by the host, 32 s) on the URL as printed."""
    return _sidbe(url, ["--no-plots"])


def link_realtime(iface: str, url: str) -> dict:
    """2 s of a ±0.8 N m square wave, paced at 1 kHz by the host, on a real-time slave."""
    from servobench.drivers.registry import open_drive

    out: dict = {}
    with open_drive(url + "&watchdog=0.5") as drive:
        drive.set_cycle(0.001)
        out["meta"], out["clock"] = drive.log_metadata(), drive.drive_clock
        drive.enable()
        u = np.where((np.arange(2000) // 250) % 2 == 0, 0.8, -0.8)
        rows, start = [], time.monotonic()
        for k, uk in enumerate(u):
            time.sleep(max(0.0, start + k * 1e-3 - time.monotonic()))
            rows.append(drive.exchange(uk))
        out["elapsed_s"] = time.monotonic() - start
        out["t"] = [r[0].t_s for r in rows]
        out["v"] = [r[0].velocity for r in rows]
        out["x"] = [r[0].position for r in rows]
        out["u"] = [r[1] for r in rows]
        out["t_act"] = [r[0].t_act_s for r in rows]
        out["recoveries"] = dict(drive.link_recoveries())
        out["reports"] = drive.reports_action_instant()
    return out


def link_late_wake(iface: str, url: str) -> dict:
    """As :func:`link_realtime`, with the host waking 1.5 ms late in the driver's SYNC0 wait at each
    of the square wave's switches (a busy machine, made to happen where it shows most)."""
    from servobench.drivers.ethercat import drive as ethercat_drive

    late = {"armed": False, "count": 0}

    class LateTime:  # the driver's time module, its sleep 1.5 ms late when armed
        def __getattr__(self, name):
            return getattr(time, name)

        def sleep(self, seconds):
            if late["armed"]:
                late["armed"] = False
                late["count"] += 1
                seconds += 1.5e-3
            time.sleep(seconds)

    from servobench.drivers.registry import open_drive

    ethercat_drive.time = LateTime()
    out: dict = {}
    with open_drive(url + "&watchdog=0.5") as drive:
        drive.set_cycle(0.001)
        drive.enable()
        u = np.where((np.arange(2000) // 250) % 2 == 0, 0.8, -0.8)
        rows, start = [], time.monotonic()
        for k, uk in enumerate(u):
            time.sleep(max(0.0, start + k * 1e-3 - time.monotonic()))
            late["armed"] = k > 0 and u[k] != u[k - 1]
            rows.append(drive.exchange(uk))
        for key, pick in (("t", lambda r: r[0].t_s), ("v", lambda r: r[0].velocity),
                          ("x", lambda r: r[0].position), ("u", lambda r: r[1]),
                          ("t_act", lambda r: r[0].t_act_s)):  # fmt: skip
            out[key] = [pick(r) for r in rows]
        out["late"] = late["count"]
        out["recoveries"] = dict(drive.link_recoveries())
    return out


def _step_errors(out: dict, acted: bool) -> np.ndarray:
    """How far each sample is from one step of the offline plant from the sample before, each
    command held from its row's instant (``acted``: from where the drive said it took force,
    ``t_act``) to the next command's."""
    t, v, x, u, t_act = (np.array(out[k], dtype=float) for k in ("t", "v", "x", "u", "t_act"))
    starts = t_act if acted else t
    plant = Plant(PARAMS)
    err = np.empty(len(t) - 1)
    for k in range(len(t) - 1):
        plant.reset(v[k], x[k])
        plant.hold(u[k], starts[k + 1] - t[k])  # (a command acts at or after its row's sample before)
        if starts[k + 1] < t[k + 1]:
            plant.hold(u[k + 1], t[k + 1] - starts[k + 1])
        err[k] = abs(plant.state.v - v[k + 1])
    return err


def link_sidbe_closed(iface: str, url: str) -> dict:
    return _sidbe(url + "&pace=fast&watchdog=2&xmin=-0.05&xmax=0.05",
                  ["--period", "2", "--periods", "3", "--no-plots"])  # fmt: skip


def link_killed_host(iface: str, url: str) -> dict:
    from servobench.drivers.registry import open_drive

    host = subprocess.Popen([sys.executable, "-c", STREAMING_HOST, url + "&watchdog=0.2"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        line = host.stdout.readline()
        if line.strip() != "streaming":
            host.wait(10)
            return {"error": host.stderr.read()}
        host.send_signal(signal.SIGKILL)
        host.wait(5)
    finally:
        if host.poll() is None:
            host.kill()
        host.stdout.close()
        host.stderr.close()
    time.sleep(0.6)  # watchdog 0.2 s, then the axis coasts with its torque off
    out: dict = {}
    with open_drive(url) as drive:
        info = drive.info()
        out["state"], out["fault"] = info.state, info.fault_code
        drive.reset_fault()
        out["after_reset"] = drive.info().state
        first = drive.read()
        time.sleep(0.2)
        second = drive.read()
        out["rest"] = [first.velocity, second.velocity, first.position, second.position]
        drive.enable()  # a new host session: the drive clock started again at open
        out["t"] = [drive.exchange(0.0)[0].t_s for _ in range(20)]
    return out


def link_no_complete_access(iface: str, url: str) -> dict:
    from servobench.drivers.registry import open_drive

    with open_drive(url) as drive:
        drive.enable()
        rows = [drive.exchange(0.8)[0] for _ in range(200)]
        return {"meta": drive.log_metadata(), "v": rows[-1].velocity, "t": rows[-1].t_s}


def link_injected(iface: str, url: str) -> dict:
    """Stream until the served drive's injected fault (or freeze) shows."""
    from servobench.drivers.registry import open_drive
    from servobench.errors import DriveFaultError

    out: dict = {"rows": []}
    with open_drive(url) as drive:
        drive.enable()
        try:
            for _ in range(2000):
                fb = drive.exchange(0.8)[0]
                out["rows"].append([fb.t_s, fb.velocity, fb.position])
        except DriveFaultError as err:
            out["fault"], out["code"] = str(err), err.code
        out["info_code"] = drive.info().fault_code
    return out


def link_cable_pulled(iface: str, url: str) -> dict:
    """The link goes down mid-run: the host says so, the slave's SM watchdog stops the axis."""
    from servobench.drivers.registry import open_drive
    from servobench.errors import DriveError

    out: dict = {}
    drive = open_drive(url + "&watchdog=0.2&frame_timeout=0.02&max_wkc_errors=5")
    drive.open()
    try:
        drive.enable()
        for _ in range(300):
            drive.exchange(1.0)
        subprocess.run(["ip", "link", "set", iface, "down"], check=True)
        t0 = time.monotonic()
        try:
            for _ in range(1000):
                drive.exchange(1.0)
        except DriveError as err:
            out["error"], out["after_s"] = str(err), time.monotonic() - t0
    finally:
        try:
            drive.close()
        except DriveError as err:
            out["close"] = str(err)
    time.sleep(0.5)
    subprocess.run(["ip", "link", "set", iface, "up"], check=True)
    time.sleep(0.2)
    with open_drive(url) as fresh:
        info = fresh.info()
        out["state"], out["fault"] = info.state, info.fault_code
    return out


def link_late_frames(iface: str, url: str, pause_s: float = 0.0) -> dict:
    from servobench.drivers.registry import open_drive
    from servobench.errors import DriveConnectionError

    out: dict = {}
    drive = open_drive(url + "&frame_timeout=0.01&max_wkc_errors=3&watchdog=1")
    drive.open()
    try:
        drive.set_cycle(0.001)
        drive.enable()
        try:
            for _ in range(5000):
                drive.exchange(0.0)
                if pause_s:
                    time.sleep(pause_s)
            out["error"] = ""
        except DriveConnectionError as err:
            out["error"] = str(err)
        out["wkc_errors"] = dict(drive.link_recoveries()).get("wkc_errors", 0)
    finally:
        try:
            drive.close()  # the quick stop may meet the same dead link: it says so
        except DriveConnectionError as err:
            out["close"] = str(err)
    return out


def link_late_frames_slow_host(iface: str, url: str) -> dict:
    """As :func:`link_late_frames` from a host 5 ms late for every frame: several SYNC0
    cycles run between two frames, the delayed one among them."""
    return link_late_frames(iface, url, pause_s=0.005)


# --------------------------------------------------------------------- tests
def test_drive_cycles_hold_and_close_against_the_served_slave() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_cycles", PLANT, LOCKSTEP)  # exact against the offline plant
    assert out["info"]["units"] == {"u": "N m", "v": "rad/s", "x": "rad"}
    assert out["info"]["product"].startswith("servobench CiA 402 drive")
    assert out["info"]["state"] == "SWITCH ON DISABLED" and out["info"]["al"] == "0x08"
    assert out["al_silent"] == [0x14, 0x1B]  # SAFE-OP + error, "sync manager watchdog"
    assert any("back in OP" in r for r in out["remarks"])
    meta = out["meta"]
    assert meta["drive_clock"].startswith("0x10F8") and out["clock"]
    assert meta["distributed_clocks"] == "SYNC0 every 1000 µs"
    assert meta["complete_access"] == "yes"
    assert meta["scale_u_source"].startswith("0x6076")
    u = np.array(out["u"])
    v_ref, x_ref = simulate(u, 1000.0, PARAMS)
    np.testing.assert_allclose(out["v"], v_ref, atol=1e-6)
    np.testing.assert_allclose(out["x"], x_ref, atol=1e-6)
    np.testing.assert_allclose(np.diff(out["t"]), 1e-3, atol=1e-9)  # lock-step DC time: cycles
    np.testing.assert_allclose(out["applied"][1:], u[:-1], atol=1e-9)  # 0x6077: the cycle before
    assert out["hold_supported"]
    assert np.max(np.abs(np.array(out["held_x"]) - out["x_ref"])) < 2e-3
    assert np.mean(np.abs(out["held_applied"])) > 0.3  # the loop holds against friction + drift
    assert out["recoveries"] == {"wkc_errors": 0}
    assert out["wd_after_close"] == 0


@pytest.mark.parametrize(
    ("serve_args", "clock"),
    [
        ([], "0x10F8 DC system time of each sample"),
        # from the grid (the slave runs at real-time priority, as every served drive of the tests)
        (
            ["--no-timestamp"],
            "DC system time of each sample (the SYNC0 event",
        ),
    ],
    ids=["timestamp", "no-timestamp"],
)
def test_real_time_slave_samples_at_the_dc_instants_the_log_gets(serve_args, clock) -> None:
    """The axis moves in wall-clock time, the slave samples at its SYNC0 events (DC-synchronous),
    and each sample is where the plant is at that DC instant with the commands as logged."""
    _link_tests()
    out = run_on_link(__file__, "link_realtime", PLANT, ["--clock", "real", *serve_args])
    assert out["meta"]["drive_clock"].startswith(clock) and out["clock"]
    assert out["meta"]["distributed_clocks"].endswith("DC-synchronous (0x1C32:01 = 2)")
    t, v, x, u = (np.array(out[k], dtype=float) for k in ("t", "v", "x", "u"))
    dt = np.diff(t)
    assert t[0] == 0.0 and np.all(dt > 0)
    assert t[-1] == pytest.approx(out["elapsed_s"], abs=0.05)  # wall-clock time, not cycles
    # on the SYNC0 grid whatever the host's timing: whole cycles, some longer than one
    np.testing.assert_allclose(dt / 1e-3, np.round(dt / 1e-3), atol=1e-6)
    assert np.max(np.abs(v)) > 0.3  # it moves both ways past the friction
    assert out["reports"]  # a DC-synchronous slave says where each command took force
    t_act = np.array(out["t_act"], dtype=float)
    assert np.all(t_act <= t)  # whole cycles before, where the host woke late
    np.testing.assert_allclose(t - t_act, 1e-3 * np.round((t - t_act) / 1e-3), atol=1e-9)
    # one step of the offline plant from each sample, each command held from where it took force
    err = _step_errors(out, acted=True)
    # a frame sent again (wkc error) has latched its command unseen: allow those steps
    bad = int(np.sum(err > 1e-4))
    assert bad <= 2 * out["recoveries"]["wkc_errors"], (bad, np.sort(err)[-5:])


def test_a_host_that_wakes_late_has_the_slave_say_where_each_command_took_force() -> None:
    """The host woke 1.5 ms late at the square wave's switches: the sample it read was the next
    SYNC0 event's, and the command had acted since the event before. Each such row says so
    (``t_act`` a cycle before ``t``) and the plant agrees with that, not with the row's instant."""
    _link_tests()
    out = run_on_link(__file__, "link_late_wake", PLANT, ["--clock", "real"])
    t, t_act = np.array(out["t"], dtype=float), np.array(out["t_act"], dtype=float)
    early = t - t_act
    assert out["late"] == 7
    switches = np.flatnonzero(np.diff(np.array(out["u"])) != 0) + 1
    assert np.count_nonzero(early[switches] > 0.5e-3) >= 5, early[switches]  # (a late wake-up
    # may still read the event it waited for, where the frame before it was early)
    np.testing.assert_allclose(early[early > 0], 1e-3 * np.round(early[early > 0] / 1e-3), atol=1e-9)
    wkc = out["recoveries"]["wkc_errors"]
    off_as_logged = int(np.sum(_step_errors(out, acted=False) > 1e-4))
    assert off_as_logged >= 5  # each late row, taken to act from its instant, misses
    assert int(np.sum(_step_errors(out, acted=True) > 1e-4)) <= 2 * wkc


def test_default_sidbe_through_the_ethercat_drive_within_one_percent() -> None:
    """A default sidbe (32 s) on a real-time slave with its DC time stamp 0x10F8."""
    _link_tests()
    out = run_on_link(__file__, "link_sidbe_open", PLANT, ["--clock", "real"])
    assert out["rc"] == 0, out["stderr"]
    model = json.loads(out["stdout"])
    note = f"model {model.get('pole')}, {model.get('dc_gain')}; stderr: {out['stderr'][-500:]}"
    assert model["pole"] == pytest.approx(-10.0, rel=0.01), note
    assert model["dc_gain"] == pytest.approx(1.0, rel=0.01), note
    assert model["coulomb_pos"] == pytest.approx(0.5, rel=0.01), note
    assert model["coulomb_neg"] == pytest.approx(0.4, rel=0.01), note
    assert model["fs"] == 1000.0 and model["loop"] == "open"
    head = out["heads"]["log.csv"]
    assert "# drive = ethercat://" in head and "# pace = real" in head
    assert "# drive_clock = 0x10F8 DC system time of each sample" in head
    assert "# late_samples = " in head  # the log's t_act says where each command acted


def test_closed_loop_sidbe_on_a_limited_travel_axis() -> None:
    _link_tests()
    # pace=fast: an algorithm test, lock-step (on a real-time slave under load, 2 runs: one passed,
    # one stopped as the hold could not keep the axis within 80 % of its 5 cm room)
    out = run_on_link(__file__, "link_sidbe_closed", NOISY, LOCKSTEP)
    assert out["rc"] == 0, out["stderr"]
    model = json.loads(out["stdout"])
    assert model["loop"] == "closed" and model["hold"]["where"] == "drive"
    assert model["pole"] == pytest.approx(-10.0, rel=0.01)
    assert model["dc_gain"] == pytest.approx(1.0, rel=0.01)
    assert model["coulomb_pos"] == pytest.approx(0.5, rel=0.05)
    assert model["coulomb_neg"] == pytest.approx(0.4, rel=0.05)


def test_killed_host_the_sm_watchdog_stops_the_axis() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_killed_host", PLANT)
    assert "error" not in out, out.get("error")
    assert out["state"] == "FAULT" and out["fault"] == 0x8130
    v1, v2, x1, x2 = out["rest"]
    assert v1 == 0.0 and v2 == 0.0 and x1 == x2 and x1 > 0.0  # it moved, then stopped
    assert out["after_reset"] == "SWITCH ON DISABLED"
    assert 0.0 <= out["t"][0] < 1.0 and np.all(np.diff(out["t"]) > 0)  # a fresh drive clock


def test_mapping_falls_back_when_complete_access_is_refused() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_no_complete_access", PLANT, ["--fault", "complete_access=0"])
    assert out["meta"]["complete_access"] == "refused: mapped entry by entry"
    assert out["meta"]["drive_clock"].startswith("0x10F8")  # the time stamp got mapped all the same
    assert out["v"] > 0.1  # 0.8 N m against 0.5 N m of friction: it runs


def test_injected_drive_fault_reaches_the_host_with_its_code() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_injected", PLANT, ["--fault", "fault@1500:0x2310"])
    assert out["code"] == 0x2310 and "0x2310" in out["fault"]
    assert out["info_code"] == 0x2310
    assert 0 < len(out["rows"]) < 1500  # the slave's cycles count its keep-alive frames too


def test_injected_freeze_keeps_the_clock_running() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_injected", PLANT, ["--fault", "freeze@600"])
    rows = np.array(out["rows"])
    assert "fault" not in out and len(rows) == 2000
    assert np.all(np.diff(rows[:, 0]) > 0)  # the drive clock runs on
    assert np.all(rows[-100:, 1:] == rows[-1, 1:]) and rows[-1, 1] > 0.1  # frozen while moving


def test_a_pulled_cable_stops_the_axis_within_the_watchdog() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_cable_pulled", PLANT)
    assert "link lost" in out["error"] and out["after_s"] < 1.0  # 5 frames of 20 ms, sent again
    assert out["state"] == "FAULT" and out["fault"] == 0x8130  # the slave stopped it alone


@pytest.mark.parametrize("host", ["link_late_frames", "link_late_frames_slow_host"])
def test_late_frames_are_counted_and_bounded(host) -> None:
    _link_tests()
    out = run_on_link(__file__, host, PLANT, ["--fault", "delay@400:100"])
    # the slow host: the delay stays pending over the SYNC0 cycles that run before its next
    # frame (it was once overwritten by them, and the run ended without the fault)
    assert "link lost" in out["error"] and "\n" not in out["error"], out
    assert out["wkc_errors"] >= 3  # the delayed frame and the two sent again while it was out


def test_without_pysoem_the_url_says_what_to_install(monkeypatch) -> None:
    from servobench.drivers.registry import open_drive
    from servobench.errors import DriveUnavailableError

    monkeypatch.setitem(sys.modules, "pysoem", None)  # import pysoem -> ImportError
    with pytest.raises(DriveUnavailableError, match=r"pip install 'servobench\[ethercat\]'") as err:
        open_drive("ethercat://eth9?slave=1").open()
    assert "\n" not in str(err.value)


def test_cli_without_pysoem_is_one_line(tmp_path) -> None:
    code = ("import sys; sys.modules['pysoem'] = None; from servobench.bench.cli import main; "
            "sys.exit(main(['sidbe', '--drive', 'ethercat://eth9', '--out', sys.argv[1]]))")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "run")],
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert out.returncode != 0
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("servobench: error:") and "pysoem" in lines[0]


@pytest.mark.parametrize(
    ("args", "says"),
    [
        ([], "needs --iface IFACE"),
        (["--iface", "nosuch0"], "nosuch0"),  # no such device, or no CAP_NET_RAW
        (["--iface", "lo", "--fault", "drop@3"], "drop applies to canopen, serial only"),
    ],
)
def test_serve_sim_ethercat_refuses_in_one_line(args, says) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "servobench", "serve-sim", "--transport", "ethercat", *args],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode != 0 and out.stdout == ""
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("servobench: error:") and says in lines[0]

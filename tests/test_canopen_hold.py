"""Issue 11, drive side: CiA 402 cyclic synchronous position holds x_ref while the host adds a torque offset.

The served drive runs its own position loop at each SYNC; the host's command
goes out as 0x60B2 and the torque the drive applied comes back in 0x6077
(``Feedback.applied``: the command of the cycle before the sample). Safety
stays: limits, quick stop, the watchdog, and a clean return to the torque
mode on release, disable and close.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from importlib import resources

import numpy as np
import pytest

from servobench.bench.testing.served_canopen import served, station
from servobench.drivers.registry import open_drive
from servobench.errors import DriveUnavailableError, LimitExceededError, UsageError
from servobench.sim_backend.device import PowerState

SIM = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
#: A host that holds a position, streams an offset, and keeps streaming until it is killed.
HOLDING_HOST = """
import sys
from servobench.drivers.registry import open_drive
drive = open_drive(sys.argv[1]).open()
drive.set_cycle(0.001)
drive.enable()
drive.hold_position(drive.exchange(0.0)[0].position + 0.5)
for _ in range(200):
    drive.exchange(0.1)
print("holding", flush=True)
while True:
    drive.exchange(0.1)
"""


def square(n: int, period: int, amp: float) -> np.ndarray:
    return np.where((np.arange(n) // (period // 2)) % 2 == 0, amp, -amp)


def _record_steps(device) -> list[float]:
    """The command the device applies in each cycle, as it steps."""
    applied: list[float] = []
    step = device.step

    def recording_step():
        applied.append(device.command)
        return step()

    device.step = recording_step
    return applied


def test_hold_keeps_x_ref_under_an_offset_and_reports_the_applied_torque() -> None:
    # host, hub and served drive share one process here: a watchdog and a TPDO wait with
    # room for a loaded test machine (this test is about the hold, not the timeouts; a
    # fresh-clone suite once waited over 100 ms for a SYNC's TPDO here)
    with served(SIM) as (device, url), open_drive(url + "&watchdog=2&pdo_timeout=1") as drive:
        assert drive.supports_drive_hold
        by_drive = _record_steps(device)
        drive.set_cycle(0.001)
        drive.enable()
        x_ref = drive.exchange(0.0)[0].position + 0.05
        drive.hold_position(x_ref)
        assert drive.holding and drive.node.sdo[0x6061].raw == 8
        u = square(2500, 400, 1.0)  # +-1 N m at 2.5 Hz: twice the Coulomb level
        rows = [drive.exchange(uk) for uk in u]
        assert drive.node.sdo[0x60B2].raw == round(1000 * u[-1])  # per mille of 1 N m rated
    fb = [r[0] for r in rows]
    x = np.array([f.position for f in fb])
    settled = x[500:]  # five whole periods of the offset
    assert np.max(np.abs(settled - x_ref)) < 0.04
    assert abs(np.mean(settled) - x_ref) < 0.003
    assert np.ptp(settled) > 0.04  # the offset does move the axis within the hold
    # Feedback.applied is what the drive applied over the cycle before the sample
    applied = np.array([f.applied for f in fb])
    np.testing.assert_allclose(applied, by_drive[: len(fb)], atol=1e-3)
    assert [r[1] for r in rows] == list(u)  # the host's own command: the offset
    assert np.max(np.abs(applied[500:] - u[499:-1])) > 0.1  # the drive's loop adds to it


def test_release_disable_and_close_return_to_the_torque_mode() -> None:
    with served(SIM) as (device, url):
        with open_drive(url) as drive:
            drive.enable()
            drive.hold_position(drive.exchange(0.0)[0].position)
            drive.exchange(0.2)
            drive.release_hold()
            assert not drive.holding and drive.node.sdo[0x6061].raw == 10
            drive.exchange(0.2)
            assert device.command == pytest.approx(0.2)  # the command is the torque again
            drive.hold_position(drive.exchange(0.0)[0].position)
            drive.disable()
            assert not drive.holding and drive.node.sdo[0x6061].raw == 10
            drive.enable()
            drive.hold_position(drive.exchange(0.0)[0].position)
            drive.exchange(0.0)  # closed while holding
        assert device.state is PowerState.DISABLED
        with station(url) as node:
            assert node.sdo[0x6061].raw == 10


def test_the_drive_limits_its_loop_to_max_torque() -> None:
    with served(SIM) as (device, url), open_drive(url + "&max_u=0.5") as drive:
        assert drive.supports_drive_hold  # the drive has 0x6072 to bound its own loop
        drive.enable()
        drive.hold_position(drive.exchange(0.0)[0].position + 5.0)
        applied = [drive.exchange(0.0)[0].applied for _ in range(50)]
        assert max(applied) == pytest.approx(0.5)
        assert device.max_command == pytest.approx(0.5)


def test_limits_and_quick_stop_hold_in_hold_mode() -> None:
    with served(SIM) as (device, url), open_drive(url + "&xmin=-0.02&xmax=0.02") as drive:
        drive.enable()
        with pytest.raises(UsageError, match="outside the allowed travel"):
            drive.hold_position(0.5)
        drive.hold_position(0.0)
        drive.exchange(0.0)
        drive.stop()
        assert device.state is PowerState.QUICK_STOP and device.command == 0.0
        drive.enable()  # transition 16, still holding
        with pytest.raises(LimitExceededError, match="outside the allowed travel"):
            for _ in range(500):
                drive.exchange(2.0)  # an offset the loop cannot hold inside +-0.02
        assert device.state is PowerState.DISABLED and not drive.holding
        assert drive.node.sdo[0x6061].raw == 10


def test_killed_host_trips_the_watchdog_while_holding() -> None:
    with served(SIM) as (device, url):
        host = subprocess.Popen(
            [sys.executable, "-c", HOLDING_HOST, url + "&watchdog=0.2"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            line = host.stdout.readline()
            assert line.strip() == "holding", (
                host.stderr.read() if host.poll() is not None else line
            )
            assert device.state is PowerState.ENABLED
            host.send_signal(signal.SIGKILL)
            host.wait(5)
        finally:
            if host.poll() is None:
                host.kill()
            host.stdout.close()
            host.stderr.close()
        deadline = time.monotonic() + 2.0
        while device.state is not PowerState.FAULT and time.monotonic() < deadline:
            time.sleep(0.01)
        assert device.state is PowerState.FAULT and device.fault_code == 0x8130
        assert device.command == 0.0


def _eds_without(tmp_path, index: int) -> str:
    """The ZeroErr object set without object ``index``."""
    text = (
        resources.files("servobench.drivers")
        .joinpath("data/zeroerr-edriver.eds")
        .read_text("ascii")
    )
    text = re.sub(rf"\[{index:04X}\]\n(?:[^\[\n].*\n|\n)*", "", text)
    text = re.sub(rf"^\d+=0x{index:04X}\n", "", text, flags=re.M)
    listed = re.search(r"\[OptionalObjects\]\nSupportedObjects=(\d+)\n((?:\d+=0x\w+\n)+)", text)
    entries = re.findall(r"=(0x\w+)", listed.group(2))
    block = f"[OptionalObjects]\nSupportedObjects={len(entries)}\n" + "".join(
        f"{i}={e}\n" for i, e in enumerate(entries, start=1)
    )
    path = tmp_path / f"zeroerr-without-{index:04X}.eds"
    path.write_text(text[: listed.start()] + block + text[listed.end() :])
    return str(path)


@pytest.mark.parametrize(
    ("eds", "extra", "reason"),
    [
        ("no-60B2", "", "0x60B2 (torque offset) absent"),
        ("zeroerr-edriver", "&max_u=1", "without max torque 0x6072"),
    ],
)
def test_a_drive_that_cannot_hold_says_why(tmp_path, eds: str, extra: str, reason: str) -> None:
    path = _eds_without(tmp_path, 0x60B2) if eds == "no-60B2" else eds
    with served(SIM, eds=path) as (_, url):
        with pytest.warns(UserWarning, match="0x6007"):
            drive = open_drive(url + extra).open()
        with drive:
            assert drive.supports_drive_hold is False
            hold = drive.log_metadata()["drive_hold"]
            assert hold.startswith("unavailable: ") and reason in hold
            drive.enable()
            with pytest.raises(DriveUnavailableError, match="host-side hold loop"):
                drive.hold_position(0.0)


def test_the_zeroerr_object_set_holds_in_increments() -> None:
    with served(SIM, eds="zeroerr-edriver") as (_, url):
        with pytest.warns(UserWarning, match="0x6007"):
            drive = open_drive(url).open()
        with drive:
            assert drive.supports_drive_hold and drive.units["x"] == "inc"
            drive.enable()
            x_ref = drive.exchange(0.0)[0].position + 2000  # increments
            drive.hold_position(x_ref)
            x = [drive.exchange(0.1)[0].position for _ in range(1500)]
            assert abs(np.mean(x[-300:]) - x_ref) < 100

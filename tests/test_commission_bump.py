"""The bump test and the drive check on the in-process simulated drive: pass, and every refusal."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from servobench.bench.commission.bump import run_bump_test
from servobench.bench.commission.checks import check_drive
from servobench.bench.commission.config import BumpSettings
from servobench.bench.commission.errors import CommissionRefused
from servobench.bench.commission.limits import ConfirmedLimits, url_with_limits
from servobench.bench.commission.ui import Console
from servobench.bench.log.io import read_log
from servobench.drivers.base import Feedback
from servobench.drivers.sim import SimDrive
from servobench.sim_backend.device import PowerState

LIMITS = ConfirmedLimits(5.0, 20.0, -100.0, 100.0)


def sim(query: str = "", cls=SimDrive) -> SimDrive:
    return cls(url_with_limits(f"sim://?pace=fast&{query}".rstrip("&"), LIMITS))


def quiet_console() -> Console:
    from rich.console import Console as RichConsole

    return Console(RichConsole(file=io.StringIO()))


def assert_disabled(drive: SimDrive) -> None:
    assert drive.device.state in (PowerState.DISABLED, PowerState.FAULT)
    assert drive.device.command == 0.0 and not drive.enabled


class Inverted(SimDrive):
    """Encoder mounted the other way round: velocity and position negated."""

    def _exchange(self, u):
        fb = super()._exchange(u)
        return Feedback(fb.t_s, -fb.velocity, -fb.position)


class BadScale(SimDrive):
    """Position counts three times what the velocity integrates to."""

    def _exchange(self, u):
        fb = super()._exchange(u)
        return Feedback(fb.t_s, fb.velocity, 3.0 * fb.position)


RPM = 2 * math.pi / 60


class WholeRpm(SimDrive):
    """A drive whose velocity (0x606C) is in whole rpm, rounded; position fine."""

    def _exchange(self, u):
        fb = super()._exchange(u)
        return Feedback(fb.t_s, RPM * round(fb.velocity / RPM), fb.position)


class WholeRpmBadScale(WholeRpm):
    """Whole rpm, and a position that counts three times what the velocity integrates to."""

    def _exchange(self, u):
        fb = super()._exchange(u)
        return Feedback(fb.t_s, fb.velocity, 3.0 * fb.position)


class InterruptAfter(SimDrive):
    """Ctrl-C after a number of cycles."""

    cycles = 120

    def _exchange(self, u):
        self.cycles -= 1
        if self.cycles < 0:
            raise KeyboardInterrupt
        return super()._exchange(u)


def bump(drive, tmp_path, settings=None):
    with drive:
        return run_bump_test(drive, LIMITS, settings or BumpSettings(), tmp_path / "bump.csv", pace="fast")


@pytest.mark.parametrize("query", ["", "noise=0.01&res_x=0.001&seed=3", "M=2&B=0.5&fc_pos=1&fc_neg=0.5"])
def test_bump_passes_on_a_sane_axis(tmp_path, query):
    drive = sim(query)
    result = bump(drive, tmp_path)
    assert result.breakaway_pos > 0 and result.breakaway_neg > 0
    assert result.position_checked
    moved = [p for p in result.pulses if p.moved]
    assert [p.amplitude > 0 for p in moved] == [True, False]
    assert all((p.peak_velocity > 0) == (p.amplitude > 0) for p in moved)
    assert_disabled(drive)
    log = read_log(result.log_path)
    assert log.complete and log.metadata["experiment"] == "bump test"


def test_bump_amplitudes_stay_small_and_escalate(tmp_path):
    result = bump(sim(), tmp_path)  # plant breaks away at 0.5 / 0.4: 0.25 and 0.5 do not move it
    amps = [p.amplitude for p in result.pulses]
    assert amps == [0.25, 0.5, 1.0, -0.25, -0.5]
    assert max(abs(a) for a in amps) <= 0.3 * LIMITS.max_u


def test_no_motion_refuses_and_leaves_the_axis_disabled(tmp_path):
    drive = sim("fc_pos=50&fc_neg=50")
    with pytest.raises(CommissionRefused, match="no motion.*positive command up to 1.5"):
        bump(drive, tmp_path)
    assert_disabled(drive)
    assert read_log(tmp_path / "bump.csv").complete


def test_wrong_direction_tells_what_to_change(tmp_path):
    drive = sim(cls=Inverted)
    with pytest.raises(CommissionRefused, match="wrong direction.*positive command gave a negative velocity.*invert"):
        bump(drive, tmp_path)
    assert_disabled(drive)


def test_position_inconsistent_with_velocity_refuses(tmp_path):
    with pytest.raises(CommissionRefused, match=r"disagree.*ratio 3"):
        bump(sim(cls=BadScale), tmp_path)


def test_signal_step_is_found_in_stepped_feedback_only():
    from servobench.bench.identify.resolution import signal_step

    rng = np.random.default_rng(0)
    smooth = np.cumsum(rng.normal(0.0, 0.01, 200))
    assert signal_step(smooth) == 0.0  # every sample distinct: no step
    assert signal_step(RPM * np.round(smooth * 20 / RPM)) == pytest.approx(RPM)
    assert signal_step(np.zeros(50)) == 0.0


def test_velocity_in_whole_rpm_is_not_mistaken_for_a_scaling_error(tmp_path):
    """Slow bumps on a drive reporting whole rpm: the integral of the stepped velocity is off
    by up to one rpm times the duration, which is not a disagreement of the two signals."""
    result = bump(sim(cls=WholeRpm), tmp_path, BumpSettings(fractions=(0.05, 0.1, 0.2, 0.4)))
    moved = [p for p in result.pulses if p.moved]
    assert moved and all(p.integral_resolution > 0 for p in moved)
    for p in moved:
        assert abs(p.displacement - p.integrated) <= p.integral_resolution + 0.25 * abs(p.displacement)


def test_a_scaling_error_is_still_found_through_whole_rpm(tmp_path):
    # pulses long and strong enough that one rpm over their duration is small against the motion
    settings = BumpSettings(fractions=(0.2, 0.4), pulse_s=0.5)
    with pytest.raises(CommissionRefused, match=r"disagree.*ratio (3|2\.9)"):
        bump(sim(cls=WholeRpmBadScale), tmp_path, settings)


def test_frozen_feedback_refuses(tmp_path):
    drive = sim()
    drive.open()
    drive.device.frozen_feedback = drive.device.sample()
    with pytest.raises(CommissionRefused, match="frozen"):
        bump(drive, tmp_path)
    assert_disabled(drive)


def test_ctrl_c_in_the_bump_test_disables_and_keeps_the_log(tmp_path):
    drive = sim(cls=InterruptAfter)
    with pytest.raises(KeyboardInterrupt):
        bump(drive, tmp_path)
    assert_disabled(drive)
    log = read_log(tmp_path / "bump.csv")
    assert not log.complete and log.metadata["reason"] == "interrupted (Ctrl-C)"
    assert sum(len(r) for r in log.runs) == 120


class StuckFault(SimDrive):
    """A drive in fault whose reset does not clear it."""

    def _open(self):
        super()._open()
        self.device.fault(0x2310, "over-current")

    def _reset_fault(self):
        pass


class ClearableFault(SimDrive):
    def _open(self):
        super()._open()
        self.device.fault(0x2310, "over-current")


def test_check_resets_a_fault_once():
    drive = sim(cls=ClearableFault)
    with drive:
        result = check_drive(drive, quiet_console(), dry_run=False, allow_reset=lambda code: True)
    assert result.fault_found == 0x2310 and result.fault_reset
    assert result.info.vendor == "servobench"


def test_check_refuses_a_fault_that_will_not_reset():
    drive = sim(cls=StuckFault)
    asked = []
    with drive, pytest.raises(CommissionRefused, match="0x2310 that will not reset"):
        check_drive(drive, quiet_console(), dry_run=False, allow_reset=lambda code: asked.append(code) or True)
    assert asked == [0x2310]
    assert_disabled(drive)


def test_check_refuses_a_declined_reset_and_only_reports_in_dry_run():
    with sim(cls=ClearableFault) as drive, pytest.raises(CommissionRefused, match="declined"):
        check_drive(drive, quiet_console(), dry_run=False, allow_reset=lambda code: False)
    with sim(cls=ClearableFault) as drive:
        console = quiet_console()
        result = check_drive(drive, console, dry_run=True, allow_reset=lambda code: True)
        assert drive.device.state is PowerState.FAULT  # dry run: no reset written
    assert result.fault_found and not result.fault_reset
    assert any("would attempt one fault reset" in line for line in console.lines)

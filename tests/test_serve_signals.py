"""``serve-sim`` stops on SIGINT/SIGTERM without a hang: the handler never takes the lock of the
event the serving loop waits on (a fresh-clone suite once saw a served CANopen drive that did not
exit within 10 s of its SIGINT)."""

from __future__ import annotations

import signal
import threading

import pytest

from servobench.bench.testing.served import ServedSim
from servobench.sim_backend.servers.serve import stop_on_signal


@pytest.mark.timeout(20)
def test_the_handler_returns_while_the_loop_holds_the_events_lock():
    # Python runs the handler in the main thread between two bytecodes, which may be inside
    # Event.wait holding the event's lock: setting the event there would wait on it forever
    stop = threading.Event()
    handler = stop_on_signal(stop)
    with stop._cond:  # where Event.wait holds it between its waits
        handler(signal.SIGINT, None)
        assert not stop.is_set()
    assert stop.wait(5.0)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_served_drive_exits_cleanly_on_its_signal(sig):
    with ServedSim("canopen", clock="lockstep") as sim:
        sim.proc.send_signal(sig)
        sim.proc.wait(10)
    assert sim.returncode == 0, sim.stderr

"""The pty link that carries the served Modbus RTU sim: byte time, frame gap, reopening."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator

import pytest
import serial

from servobench.bench.testing.served import DRIVE_PRIORITY
from servobench.sim_backend.servers.modbus.serve_modbus import rtu_frame_gap_s
from servobench.sim_backend.servers.pty_link import PtyLink


@contextlib.contextmanager
def as_hardware() -> Iterator[None]:
    """This thread, and the link's pump thread it starts (Linux threads inherit the policy),
    at the served drives' real-time priority where permitted: a wire and a device do not wait
    for a time-shared scheduler, so a timing the test measures is the link's own, not the
    load's. Reverted at exit."""
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(DRIVE_PRIORITY))
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, before[0], before[1])


def test_passes_bytes_both_ways_and_survives_reopen():
    with PtyLink() as link:
        a = serial.Serial(link.a_path, timeout=1)
        b = serial.Serial(link.b_path, timeout=1)
        a.write(b"\x01\x03\x00\x00")
        assert b.read(4) == b"\x01\x03\x00\x00"
        b.write(b"pong")
        assert a.read(4) == b"pong"
        a.close()  # a killed host: its end closes
        a = serial.Serial(link.a_path, timeout=1)  # a fresh client on the same path
        a.write(b"again")
        assert b.read(5) == b"again"
        a.close()
        b.close()
    link.close()  # safe twice


@pytest.mark.parametrize("n", [8, 40])
def test_frames_take_their_line_time(n):
    baud, gap = 115200, rtu_frame_gap_s(115200)
    expected_s = n * 10 / baud + gap
    with as_hardware(), PtyLink(baud=baud, frame_gap_s=gap) as link:
        a = serial.Serial(link.a_path, timeout=1)
        b = serial.Serial(link.b_path, timeout=1)
        for _ in range(3):
            t0 = time.monotonic()
            a.write(bytes(range(n)))
            assert b.read(n) == bytes(range(n))
            elapsed = time.monotonic() - t0
            assert elapsed >= expected_s  # never faster than the wire
            assert elapsed < expected_s + 0.02
        a.close()
        b.close()


def test_back_to_back_frames_keep_the_silence_between_them():
    baud, gap = 19200, rtu_frame_gap_s(19200)
    assert gap == pytest.approx(3.5 * 11 / 19200)
    with PtyLink(baud=baud, frame_gap_s=gap) as link:
        a = serial.Serial(link.a_path, timeout=1)
        b = serial.Serial(link.b_path, timeout=1)
        t0 = time.monotonic()
        a.write(bytes(10))
        time.sleep(0.006)  # the first frame is off the wire at 5.2 ms, its silence lasts to 7.2 ms
        a.write(bytes(10))
        assert len(b.read(20)) == 20
        # the second frame waits for the first one's silence: 2 x (5.2 + 2.0) ms, not 6 + 7.2 ms
        assert time.monotonic() - t0 >= 2 * (10 * 10 / baud + gap)
        a.close()
        b.close()


def test_rejects_nonsense():
    with pytest.raises(ValueError):
        PtyLink(baud=0)
    with pytest.raises(ValueError):
        PtyLink(frame_gap_s=-1.0)

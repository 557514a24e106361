"""The pty link that carries the served Modbus RTU sim: byte time, frame gap, reopening."""

from __future__ import annotations

import time

import pytest
import serial

from servobench.bench.testing.served import at_drive_priority
from servobench.sim_backend.servers.modbus.serve_modbus import rtu_frame_gap_s
from servobench.sim_backend.servers.pty_link import PtyLink


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
    with at_drive_priority(), PtyLink(baud=baud, frame_gap_s=gap) as link:
        a = serial.Serial(link.a_path, timeout=1)
        b = serial.Serial(link.b_path, timeout=1)
        took = []
        for _ in range(5):
            t0 = time.monotonic()
            a.write(bytes(range(n)))
            assert b.read(n) == bytes(range(n))
            took.append(time.monotonic() - t0)
        assert min(took) >= expected_s  # never faster than the wire
        # and no slower than it: a loaded host may hold up any one frame (a fresh-clone suite
        # once took 35.7 ms for the 25.2 ms allowed), so the fastest of five is held to it
        assert min(took) < expected_s + 0.02, took
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

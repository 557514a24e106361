"""Fuzz the serial line parser on both sides: any bytes give a value or one typed error.

Host side: :func:`servobench.drivers.serial.ascii_line.decode_reply` and
:meth:`servobench.drivers.serial.dialect.Dialect.parse_reply` (a reply line is parsed, or
:class:`~servobench.drivers.serial.ascii_line.MalformedReplyError` in one line; parsed floats
are finite). Drive side: the served dialect's request handler answers any
line with bytes (possibly none) and never raises.
"""

from __future__ import annotations

import math

from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from servobench.drivers.serial.ascii_line import (
    MalformedReplyError,
    decode_reply,
    decode_request,
    xor_checksum,
)
from servobench.drivers.serial.dialect import REPLY_FIELDS, load_dialect
from servobench.sim_backend.device import SimulatedDevice
from servobench.sim_backend.physics.plant import PlantParams
from servobench.sim_backend.servers.serial.serve_serial import AsciiDriveServer

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ODRIVE = load_dialect("odrive")
_TOKENS = st.sampled_from(
    ["0", "-1", "0.5", "1e999", "-1e-999", "nan", "inf", "0x1F", "+.5", " ", "  ", "*", "*93",
     "r", "w", "c", "f", "axis0.error", "vbus_voltage", "0 ", "\t", "\x00", "é", ";", "\r"]
)  # fmt: skip
LINES = st.one_of(
    st.binary(max_size=40),
    st.lists(_TOKENS, max_size=6).map(lambda t: " ".join(t).encode("utf-8")),
)


def check_error(err: MalformedReplyError) -> None:
    message = str(err)
    assert message and len(message.splitlines()) == 1, repr(message)


@FUZZ
@given(LINES, st.booleans(), st.sampled_from(sorted(REPLY_FIELDS)))
@example(b"1e999 0", False, "feedback")
@example(b"0.5 0.25*" + str(xor_checksum("0.5 0.25")).encode(), True, "feedback")
@example(b"0x7fffffffffffffffffff", False, "error")
def test_reply_lines(raw: bytes, checksum: bool, reply: str) -> None:
    try:
        body = decode_reply(raw, checksum)
        parsed = ODRIVE.parse_reply(reply, body)
    except MalformedReplyError as err:
        check_error(err)
        return
    assert set(parsed.fields) == set(REPLY_FIELDS[reply])
    for value in parsed.fields.values():
        assert not isinstance(value, float) or math.isfinite(value)


@FUZZ
@given(LINES)
@example(b"c 0 1e999")
@example(b"w axis0.config.watchdog_timeout -1")
@example(b"w axis0.config.servobench_cycle 0")
@example(b"w axis0.config.servobench_cycle 1e-320")
@example(b"f 0*118")
def test_served_drive_answers_any_request_line(raw: bytes) -> None:
    device = SimulatedDevice(PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4))
    server = AsciiDriveServer(device, ODRIVE)
    for line in (raw, b"f 0", raw):  # and it still works afterwards
        reply = server.handle(line)
        assert isinstance(reply, bytes)
    assert decode_request(raw).body == decode_request(raw).body  # pure, total
    assert math.isfinite(device.command) and math.isfinite(device.plant.state.x)

"""The socketcand codec (golden vectors, python-can interop) and the TCP hub."""

from __future__ import annotations

import socket
import struct
import threading
import time

import can
import pytest
from can.interfaces.socketcand.socketcand import (
    convert_ascii_message_to_can_message,
    convert_can_message_to_ascii_message,
)

from servobench.sim_backend.servers.canopen.socketcand_server import SocketcandHub
from servobench.sim_backend.servers.canopen.wire import (
    CanFrame,
    WireError,
    encode_frame,
    encode_send,
    parse_frame,
    parse_send,
    split_commands,
)

FRAMES = [
    CanFrame(0x000, b""),
    CanFrame(0x080, b""),
    CanFrame(0x182, bytes([0x27, 0x02, 0xE8, 0x03, 0x10, 0x27, 0x00, 0x00])),
    CanFrame(0x7FF, b"\x00\x0f\xf0"),
    CanFrame(0x1ABCDEF, b"\x01", is_extended=True),
]


@pytest.mark.parametrize(
    ("frame", "send", "delivered"),
    [
        (
            CanFrame(0x202, b"\x0f\x00\xe8\x03"),
            "< send 202 4 f 0 e8 3 >",
            "< frame 202 12.500000 0F00E803 >",
        ),
        (CanFrame(0x080, b""), "< send 080 0 >", "< frame 080 12.500000  >"),
        (
            CanFrame(0x12345, b"\xff", True),
            "< send 00012345 1 ff >",
            "< frame 00012345 12.500000 FF >",
        ),
    ],
)
def test_golden_vectors(frame: CanFrame, send: str, delivered: str) -> None:
    assert encode_send(frame) == send
    assert parse_send(send) == frame
    assert encode_frame(frame, 12.5) == delivered
    assert parse_frame(delivered) == (frame, 12.5)


@pytest.mark.parametrize("frame", FRAMES)
def test_codec_matches_python_can(frame: CanFrame) -> None:
    msg = can.Message(
        arbitration_id=frame.can_id, data=frame.data, is_extended_id=frame.is_extended
    )
    assert parse_send(convert_can_message_to_ascii_message(msg)) == frame
    back = convert_ascii_message_to_can_message(encode_frame(frame, 1700000000.25))
    assert (back.arbitration_id, bytes(back.data), back.is_extended_id) == (
        frame.can_id,
        frame.data,
        frame.is_extended,
    )
    assert back.timestamp == pytest.approx(1700000000.25)


def test_split_commands_keeps_the_unfinished_tail() -> None:
    assert split_commands("< hi >< ok >< send 1") == (["< hi >", "< ok >"], "< send 1")
    assert split_commands("junk< ok >junk") == (["< ok >"], "")


@pytest.mark.parametrize(
    "bad",
    ["< send 123 2 1 >", "< send 800 0 >", "< send xyz 0 >", "< send 123 9 1 2 3 4 5 6 7 8 9 >"],
)
def test_malformed_send_is_rejected(bad: str) -> None:
    with pytest.raises(WireError):
        parse_send(bad)


def _bus(hub: SocketcandHub, channel: str = "vcan0") -> can.BusABC:
    host, port = hub.address
    return can.Bus(interface="socketcand", channel=channel, host=host, port=port, tcp_tune=True)


def _recv_all(bus: can.BusABC, n: int, timeout_s: float = 2.0) -> list[can.Message]:
    out, deadline = [], time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        msg = bus.recv(0.1)
        if msg is not None:
            out.append(msg)
    return out


def test_hub_is_a_bus_for_python_can_clients_and_local_ports() -> None:
    local: list[CanFrame] = []
    with SocketcandHub() as hub:
        port = hub.attach(local.append)
        a, b = _bus(hub), _bus(hub)
        try:
            for frame in FRAMES:
                a.send(
                    can.Message(
                        arbitration_id=frame.can_id,
                        data=frame.data,
                        is_extended_id=frame.is_extended,
                    )
                )
            got = _recv_all(b, len(FRAMES))
            assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in got] == [
                (f.can_id, f.data, f.is_extended) for f in FRAMES
            ]
            deadline = time.monotonic() + 2.0
            while len(local) < len(FRAMES) and time.monotonic() < deadline:
                time.sleep(0.01)
            assert local == FRAMES
            assert a.recv(0.05) is None  # a station does not hear itself
            port.send(CanFrame(0x701, b"\x05"))
            for bus in (a, b):
                (msg,) = _recv_all(bus, 1)
                assert (msg.arbitration_id, bytes(msg.data)) == (0x701, b"\x05")
            assert hub.client_count == 2
        finally:
            a.shutdown()
            b.shutdown()
        deadline = time.monotonic() + 2.0
        while hub.client_count and time.monotonic() < deadline:
            time.sleep(0.01)
        assert hub.client_count == 0


def test_hub_refuses_an_unknown_channel() -> None:
    with SocketcandHub() as hub, pytest.raises(can.CanError, match="error"):
        _bus(hub, channel="can7")


def _raw_client(hub: SocketcandHub) -> socket.socket:
    """A bare TCP client through socketcand's handshake, in raw mode."""
    sock = socket.create_connection(hub.address, timeout=5)
    assert _reply(sock) == "< hi >"
    for command in ("< open vcan0 >", "< rawmode >"):
        sock.sendall(command.encode())
        assert _reply(sock) == "< ok >"
    return sock


def _reply(sock: socket.socket) -> str:
    """One ``< ... >`` reply (read byte by byte, so nothing after it is taken)."""
    text = ""
    while not text.endswith(">") or text.count("<") != text.count(">"):
        byte = sock.recv(1)
        assert byte, f"connection closed after {text!r}"
        text += byte.decode("ascii")
        if len(text) > 200:
            break
    return text


def test_error_replies_have_socketcands_form_without_nested_brackets() -> None:
    """socketcand answers an unknown command with ``< error unknown command >``
    (state_raw.c, state_nobus.c); no reply carries a bracket inside its text."""
    with SocketcandHub() as hub:
        sock = _raw_client(hub)
        try:
            sock.sendall(b"< subscribe 0 0 123 >")  # a BCM-mode command, not served in raw mode
            assert _reply(sock) == "< error unknown command >"
            sock.sendall(b"< send 12G 1 5 >")  # not a hex id
            reply = _reply(sock)
            assert reply.startswith("< error ") and reply.endswith(" >"), reply
            assert reply.count("<") == reply.count(">") == 1, reply
        finally:
            sock.close()
        with socket.create_connection(hub.address, timeout=5) as sock:
            assert _reply(sock) == "< hi >"
            sock.sendall(b"< open can7 >")
            reply = _reply(sock)
            assert reply.startswith("< error ") and reply.count("<") == reply.count(">") == 1, reply


def test_a_new_client_gets_every_frame_sent_after_its_rawmode_is_acknowledged() -> None:
    """python-can's client is connected (its ``< rawmode >`` acknowledged) when ``can.Bus``
    returns: from there on, no frame another station sends may be missing, even before the
    new client has sent anything itself."""
    sent = [0]
    stop = threading.Event()
    with SocketcandHub() as hub:
        port = hub.attach(lambda frame: None)

        def count() -> None:  # a station sending a numbered frame every millisecond
            while not stop.is_set():
                port.send(CanFrame(0x181, struct.pack("<I", sent[0])))
                sent[0] += 1
                time.sleep(0.001)

        sender = threading.Thread(target=count, daemon=True)
        sender.start()
        try:
            time.sleep(0.05)
            bus = _bus(hub)
            joined = sent[0]  # frames numbered from here on were sent after the acknowledgement
            try:
                got: list[int] = []
                deadline = time.monotonic() + 10.0
                while (not got or got[-1] < joined + 300) and time.monotonic() < deadline:
                    msg = bus.recv(0.5)
                    if msg is not None:
                        got.append(struct.unpack("<I", msg.data)[0])
            finally:
                bus.shutdown()
        finally:
            stop.set()
            sender.join(2)
    assert got, "no frame reached the new client"
    assert got[0] <= joined, f"frames {joined}..{got[0] - 1} sent after the join were lost"
    assert got == list(range(got[0], got[0] + len(got))), "a frame was lost or reordered"

"""Golden EtherCAT frames: bytes written from the specification's layouts, not from the codec.

Each frame below is spelled out byte by byte from ETG.1000.4 (Ethernet header,
EtherCAT header ``length | type 1 << 12``, datagram ``cmd idx ADP ADO
len|flags IRQ data WKC``) and ETG.1000.6 (mailbox, CoE, SDO); the served
slave (:func:`servobench.sim_backend.servers.ethercat.serve_ethercat.answer`,
in-process, no socket) must return exactly the expected bytes: data, working
counter, ADP of the auto-increment and broadcast commands, and the source
address with its locally administered bit set.
"""

from __future__ import annotations

import pytest

from servobench.sim_backend.device import device_from_url
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.spec import FaultPlan
from servobench.sim_backend.servers.ethercat.coe_drive import CoeSlave
from servobench.sim_backend.servers.ethercat.serve_ethercat import answer

DST = bytes.fromhex("ffffffffffff")
SRC = bytes.fromhex("010101010101")
SRC_BACK = bytes.fromhex("030101010101")
ETHERTYPE = bytes.fromhex("88a4")


def frame(*datagrams: bytes) -> bytes:
    body = b"".join(datagrams)
    header = (len(body) | 0x1000).to_bytes(2, "little")
    raw = DST + SRC + ETHERTYPE + header + body
    return raw + bytes(max(0, 60 - len(raw)))


def returned(*datagrams: bytes) -> bytes:
    return SRC_BACK.join(frame(*datagrams).split(SRC, 1))


def dg(cmd: int, adp: int, ado: int, data: bytes, wkc: int = 0, more: bool = False) -> bytes:
    """A datagram from the table of ETG.1000.4: ``cmd idx ADP ADO len IRQ data WKC``."""
    length = len(data) | (0x8000 if more else 0)
    return (bytes([cmd, 0x5A]) + adp.to_bytes(2, "little") + ado.to_bytes(2, "little")
            + length.to_bytes(2, "little") + b"\x00\x00" + data + wkc.to_bytes(2, "little"))  # fmt: skip


APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = (
    1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14,
)  # fmt: skip
STATION = 0x1001


@pytest.fixture
def slave() -> CoeSlave:
    device = device_from_url("sim://?M=0.1&B=1", wall_clock=True)
    return CoeSlave(device, FaultInjector(device, FaultPlan("ethercat")))


def exchange(slave: CoeSlave, request: bytes) -> bytes:
    reply = answer(slave, request)
    assert reply is not None
    return reply


def addressed(slave: CoeSlave) -> None:
    exchange(slave, frame(dg(APWR, 0x0000, 0x0010, STATION.to_bytes(2, "little"))))


def test_brd_type_register_counts_one_slave_and_increments_adp(slave: CoeSlave) -> None:
    request = frame(dg(BRD, 0x0000, 0x0000, b"\x00\x00"))
    # type 0x11, revision 0x02; working counter 1; ADP incremented
    assert exchange(slave, request) == returned(dg(BRD, 0x0001, 0x0000, b"\x11\x02", 1))


def test_aprd_addresses_position_zero_only(slave: CoeSlave) -> None:
    first = frame(dg(APRD, 0x0000, 0x0130, b"\x00\x00"))
    assert exchange(slave, first) == returned(dg(APRD, 0x0001, 0x0130, b"\x01\x00", 1))
    second = frame(dg(APRD, 0xFFFF, 0x0130, b"\x00\x00"))  # position -1: the next slave
    assert exchange(slave, second) == returned(dg(APRD, 0x0000, 0x0130, b"\x00\x00", 0))


def test_station_address_then_fprd_and_a_miss(slave: CoeSlave) -> None:
    request = frame(dg(APWR, 0x0000, 0x0010, b"\x01\x10"))
    assert exchange(slave, request) == returned(dg(APWR, 0x0001, 0x0010, b"\x01\x10", 1))
    hit = frame(dg(FPRD, STATION, 0x0010, b"\x00\x00"))
    assert exchange(slave, hit) == returned(dg(FPRD, STATION, 0x0010, b"\x01\x10", 1))
    miss = frame(dg(FPRD, 0x1002, 0x0010, b"\x00\x00"))
    assert exchange(slave, miss) == returned(dg(FPRD, 0x1002, 0x0010, b"\x00\x00", 0))


def test_two_datagrams_in_one_frame_keep_their_order(slave: CoeSlave) -> None:
    request = frame(
        dg(BRD, 0x0000, 0x0000, b"\x00", more=True), dg(BRD, 0x0000, 0x0005, b"\x00")
    )  # type, then the number of SyncManagers (8)
    assert exchange(slave, request) == returned(
        dg(BRD, 0x0001, 0x0000, b"\x11", 1, more=True), dg(BRD, 0x0001, 0x0005, b"\x08", 1)
    )


def test_read_only_register_ignores_the_write_but_counts_it(slave: CoeSlave) -> None:
    addressed(slave)
    exchange(slave, frame(dg(FPWR, STATION, 0x0000, b"\x99")))  # ESC type: read only
    reply = exchange(slave, frame(dg(FPRD, STATION, 0x0000, b"\x00")))
    assert reply == returned(dg(FPRD, STATION, 0x0000, b"\x11", 1))


def test_bwr_aprw_brw_write_and_count(slave: CoeSlave) -> None:
    # BWR the watchdog divider (0x0400) to 0x09C2: one slave wrote it, ADP incremented
    request = frame(dg(BWR, 0x0000, 0x0400, b"\xc2\x09"))
    assert exchange(slave, request) == returned(dg(BWR, 0x0001, 0x0400, b"\xc2\x09", 1))
    # APRW the station address at position 0: the old value (0) read back, the new written (+1 +2)
    request = frame(dg(APRW, 0x0000, 0x0010, b"\x05\x10"))
    assert exchange(slave, request) == returned(dg(APRW, 0x0001, 0x0010, b"\x00\x00", 3))
    reply = exchange(slave, frame(dg(FPRD, 0x1005, 0x0010, b"\x00\x00")))
    assert reply == returned(dg(FPRD, 0x1005, 0x0010, b"\x05\x10", 1))
    # BRW of the PD watchdog time (1000 = 0x03E8 after reset): the old value ORed into the
    # frame's 0x01F4, which is written
    request = frame(dg(BRW, 0x0000, 0x0420, b"\xf4\x01"))
    assert exchange(slave, request) == returned(dg(BRW, 0x0001, 0x0420, b"\xfc\x03", 3))
    reply = exchange(slave, frame(dg(FPRD, 0x1005, 0x0420, b"\x00\x00")))
    assert reply == returned(dg(FPRD, 0x1005, 0x0420, b"\xf4\x01", 1))


def test_fprw_counts_three_and_returns_the_old_value(slave: CoeSlave) -> None:
    addressed(slave)
    request = frame(dg(FPRW, STATION, 0x0420, b"\x64\x00"))  # PD watchdog 1000 -> 100
    assert exchange(slave, request) == returned(dg(FPRW, STATION, 0x0420, b"\xe8\x03", 3))
    reply = exchange(slave, frame(dg(FPRD, STATION, 0x0420, b"\x00\x00")))
    assert reply == returned(dg(FPRD, STATION, 0x0420, b"\x64\x00", 1))


def test_al_control_skipping_states_sets_the_error_and_code_0x0011(slave: CoeSlave) -> None:
    addressed(slave)
    exchange(slave, frame(dg(FPWR, STATION, 0x0120, b"\x08\x00")))  # INIT -> OP: no
    reply = exchange(slave, frame(dg(FPRD, STATION, 0x0130, bytes(6))))
    # AL status INIT | error flag, reserved, AL status code 0x0011
    assert reply == returned(dg(FPRD, STATION, 0x0130, b"\x11\x00\x00\x00\x11\x00", 1))
    exchange(slave, frame(dg(FPWR, STATION, 0x0120, b"\x11\x00")))  # INIT + acknowledge
    reply = exchange(slave, frame(dg(FPRD, STATION, 0x0130, bytes(6))))
    assert reply == returned(dg(FPRD, STATION, 0x0130, b"\x01\x00\x00\x00\x00\x00", 1))


def test_eeprom_read_of_the_identity(slave: CoeSlave) -> None:
    addressed(slave)
    # control: read command (0x0100), word address 0x0008 (vendor id, product code)
    exchange(slave, frame(dg(FPWR, STATION, 0x0502, b"\x00\x01\x08\x00\x00\x00")))
    status = exchange(slave, frame(dg(FPRD, STATION, 0x0502, b"\x00\x00")))
    assert status == returned(dg(FPRD, STATION, 0x0502, b"\x40\x00", 1))  # idle, 8-byte reads
    data = exchange(slave, frame(dg(FPRD, STATION, 0x0508, bytes(8))))
    expected = b"\x00\x00\x00\x00" + b"\x02\x04\x00\x00"  # vendor 0, product 0x00000402
    assert data == returned(dg(FPRD, STATION, 0x0508, expected, 1))


def test_fmmu_logical_write_read_and_lrw(slave: CoeSlave) -> None:
    addressed(slave)
    # FMMU0: logical 0x00010000, 4 bytes, bits 0..7 -> physical 0x1800, write; FMMU1 the same, read
    fmmu0 = bytes.fromhex("00000100040000070018000201000000")
    fmmu1 = bytes.fromhex("00000100040000070018000101000000")
    exchange(slave, frame(dg(FPWR, STATION, 0x0600, fmmu0 + fmmu1)))
    write = frame(dg(LWR, 0x0000, 0x0001, b"\xde\xad\xbe\xef"))  # logical address LE: 0x00010000
    assert exchange(slave, write) == returned(dg(LWR, 0x0000, 0x0001, b"\xde\xad\xbe\xef", 1))
    read = frame(dg(LRD, 0x0000, 0x0001, bytes(4)))
    assert exchange(slave, read) == returned(dg(LRD, 0x0000, 0x0001, b"\xde\xad\xbe\xef", 1))
    both = frame(dg(LRW, 0x0000, 0x0001, b"\x01\x02\x03\x04"))
    assert exchange(slave, both) == returned(dg(LRW, 0x0000, 0x0001, b"\x01\x02\x03\x04", 3))
    elsewhere = frame(dg(LRD, 0x0000, 0x0002, bytes(4)))  # 0x00020000: no FMMU
    assert exchange(slave, elsewhere) == returned(dg(LRD, 0x0000, 0x0002, bytes(4), 0))


def test_frmw_reads_the_reference_clock_armw_elsewhere_writes(slave: CoeSlave) -> None:
    addressed(slave)
    reply = exchange(slave, frame(dg(FRMW, STATION, 0x0910, bytes(8))))
    body = reply[14 + 2 :]
    assert body[10:18] != bytes(8) and int.from_bytes(body[18:20], "little") == 1
    # ARMW at position 1: this slave is not the reader, it takes the time (wkc 1, data kept)
    time = (123456789).to_bytes(8, "little")
    reply = exchange(slave, frame(dg(ARMW, 0xFFFF, 0x0910, time)))
    assert reply == returned(dg(ARMW, 0x0000, 0x0910, time, 1))


def test_sdo_upload_through_the_mailbox(slave: CoeSlave) -> None:
    addressed(slave)
    # SM0 0x1000 128 bytes control 0x26 enabled; SM1 0x1080 128 bytes control 0x22 enabled
    sms = bytes.fromhex("00108000260001008010800022000100")
    exchange(slave, frame(dg(FPWR, STATION, 0x0800, sms)))
    exchange(slave, frame(dg(FPWR, STATION, 0x0120, b"\x02\x00")))  # PRE-OP
    state = exchange(slave, frame(dg(FPRD, STATION, 0x0130, b"\x00\x00")))
    assert state == returned(dg(FPRD, STATION, 0x0130, b"\x02\x00", 1))
    empty = exchange(slave, frame(dg(FPRD, STATION, 0x1080, bytes(128))))
    assert empty == returned(dg(FPRD, STATION, 0x1080, bytes(128), 0))  # empty: refused
    # mailbox: length 10, address 0, channel 0, type CoE (3) counter 1; CoE: SDO request (2 << 12);
    # SDO: upload request 0x40, index 0x1000, sub 0
    request = bytes.fromhex("0a000000001300204000100000000000")
    mbx = request + bytes(128 - len(request))
    assert exchange(slave, frame(dg(FPWR, STATION, 0x1000, mbx))) == returned(
        dg(FPWR, STATION, 0x1000, mbx, 1)
    )
    status = exchange(slave, frame(dg(FPRD, STATION, 0x080D, b"\x00")))
    assert status == returned(dg(FPRD, STATION, 0x080D, b"\x08", 1))  # SM1 mailbox full
    # answer: SDO response (3 << 12), expedited 4 bytes 0x43, 0x1000:00 = 0x00020192
    response = bytes.fromhex("0a000000001300304300100092010200")
    expected = response + bytes(128 - len(response))
    reply = exchange(slave, frame(dg(FPRD, STATION, 0x1080, bytes(128))))
    assert reply == returned(dg(FPRD, STATION, 0x1080, expected, 1))
    status = exchange(slave, frame(dg(FPRD, STATION, 0x080D, b"\x00")))
    assert status == returned(dg(FPRD, STATION, 0x080D, b"\x00", 1))  # read: empty again


def test_sdo_abort_code_through_the_mailbox(slave: CoeSlave) -> None:
    addressed(slave)
    sms = bytes.fromhex("00108000260001008010800022000100")
    exchange(slave, frame(dg(FPWR, STATION, 0x0800, sms)))
    exchange(slave, frame(dg(FPWR, STATION, 0x0120, b"\x02\x00")))
    request = bytes.fromhex("0a000000002300204000600000000000")  # 0x6000
    exchange(slave, frame(dg(FPWR, STATION, 0x1000, request + bytes(128 - len(request)))))
    # abort: CoE service SDO request (2), command 0x80, 0x6000:00, code 0x06020000
    abort = bytes.fromhex("0a000000002300208000600000000206")
    reply = exchange(slave, frame(dg(FPRD, STATION, 0x1080, bytes(128))))
    assert reply == returned(dg(FPRD, STATION, 0x1080, abort + bytes(128 - len(abort)), 1))


def test_frames_of_other_kinds_are_not_answered(slave: CoeSlave) -> None:
    assert answer(slave, DST + SRC + bytes.fromhex("0800") + bytes(46)) is None  # IPv4
    assert answer(slave, frame(dg(BRD, 0, 0, b"\x00"))[:20]) is None  # truncated
    processed = SRC_BACK.join(frame(dg(BRD, 0, 0, b"\x00")).split(SRC, 1))
    assert answer(slave, processed) is None  # already passed a slave: returning

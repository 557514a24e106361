"""The served EtherCAT slave's layers in-process: AL table, codec, SDO segments, PDO rules, SM checks.

Expectations are written from the specifications (ETG.1000.6 AL state
transitions and status codes, CiA 301 SDO segment protocol and abort codes),
not read back from the modules under test.
"""

from __future__ import annotations

import struct

import pytest

from servobench.sim_backend.device import device_from_url
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.spec import FaultPlan
from servobench.sim_backend.servers.ethercat import al
from servobench.sim_backend.servers.ethercat.coe_drive import CoeSlave
from servobench.sim_backend.servers.ethercat.coe_sdo import SdoServer
from servobench.sim_backend.servers.ethercat.frame import (
    Command,
    Datagram,
    Frame,
    FrameError,
    decode_frame,
    encode_frame,
)
from servobench.sim_backend.servers.ethercat.mailbox import decode_mailbox

A = al.AlState
#: ETG.1000.6 figure 23: the transitions a master may request (beside staying).
ALLOWED = {
    (A.INIT, A.PRE_OP), (A.INIT, A.BOOT), (A.PRE_OP, A.INIT), (A.PRE_OP, A.SAFE_OP),
    (A.SAFE_OP, A.INIT), (A.SAFE_OP, A.PRE_OP), (A.SAFE_OP, A.OP), (A.OP, A.INIT),
    (A.OP, A.PRE_OP), (A.OP, A.SAFE_OP), (A.BOOT, A.INIT),
}  # fmt: skip


@pytest.mark.parametrize("current", list(A))
@pytest.mark.parametrize("requested", [*list(A), 0x05, 0x06, 0x07, 0x09, 0x0F])
def test_al_transition_table(current, requested) -> None:
    code = al.check_request(current, al.decode_control(int(requested)))
    if not isinstance(requested, A):
        assert code == 0x0012  # unknown requested state
    elif requested is current or (current, requested) in ALLOWED:
        assert code == 0x0000
    else:
        assert code == 0x0011  # invalid requested state change


def test_frame_codec_round_trip_and_malformed_frames() -> None:
    dgs = (Datagram(Command.FPRD, 7, 0x1001, 0x0130, b"\x00\x00", 1),
           Datagram.logical(Command.LRW, 8, 0x00010000, b"\x01\x02\x03"))  # fmt: skip
    frame = Frame(b"\xff" * 6, b"\x01" * 6, dgs)
    raw = encode_frame(frame)
    assert len(raw) == 60 and decode_frame(raw) == frame
    with pytest.raises(FrameError, match="EtherType"):
        decode_frame(raw[:12] + b"\x08\x00" + raw[14:])
    with pytest.raises(FrameError, match="overruns"):
        decode_frame(raw[:14] + b"\xff\x17" + raw[16:])  # header length 0x7FF
    with pytest.raises(FrameError, match="type"):
        decode_frame(raw[:14] + b"\x1c\x20" + raw[16:])  # type 2


@pytest.fixture
def slave() -> CoeSlave:
    device = device_from_url("sim://?M=0.1&B=1", wall_clock=True)
    return CoeSlave(device, FaultInjector(device, FaultPlan("ethercat")))


def _sdo(server: SdoServer, body: bytes) -> bytes:
    """One request: mailbox (length, address 0, channel 0, CoE, counter 1), CoE SDO request."""
    data = b"\x00\x20" + body
    raw = struct.pack("<HHBB", len(data), 0, 0, 0x13) + data
    reply = decode_mailbox(server.handle(decode_mailbox(raw)))
    return reply.data[2:]


def test_segmented_upload_through_a_small_mailbox(slave: CoeSlave) -> None:
    server = SdoServer(slave.node, mailbox_bytes=32)  # 16 data bytes in the initiate response
    name = b"servobench CiA 402 drive"
    first = _sdo(server, bytes([0x40]) + struct.pack("<HB", 0x1008, 0) + bytes(4))
    assert first[0] == 0x41 and struct.unpack_from("<I", first, 4)[0] == len(name)
    got, toggle = first[8:], 0x00
    while True:
        seg = _sdo(server, bytes([0x60 | toggle]) + bytes(7))
        assert seg[0] & 0xE0 == 0x00 and seg[0] & 0x10 == toggle  # upload segment response
        chunk = seg[1:]
        if seg[0] & 0x01:  # last: n unused bytes of the 7
            got += chunk[: len(chunk) - (seg[0] >> 1 & 0x07)] if len(chunk) == 7 else chunk
            break
        got += chunk
        toggle ^= 0x10
    assert got == name


def test_toggle_error_aborts_with_0x05030000(slave: CoeSlave) -> None:
    server = SdoServer(slave.node, mailbox_bytes=32)
    _sdo(server, bytes([0x40]) + struct.pack("<HB", 0x1008, 0) + bytes(4))
    reply = _sdo(server, bytes([0x70]) + bytes(7))  # toggle 1 where 0 is due
    assert reply[0] == 0x80 and struct.unpack_from("<I", reply, 4)[0] == 0x05030000


def test_segmented_complete_access_download_of_a_mapping(slave: CoeSlave) -> None:
    server = SdoServer(slave.node, mailbox_bytes=32)
    entries = [0x60410010, 0x60640020, 0x606C0020, 0x60770010, 0x10130020, 0x60610008,
               0x00000008, 0x60410010]  # fmt: skip
    data = struct.pack("<Bx8I", 5, *entries)  # 34 bytes: count, padding, all 8 entries
    first = _sdo(server, bytes([0x31]) + struct.pack("<HBI", 0x1A00, 0, len(data)) + data[:16])
    assert first[0] == 0x60
    rest, toggle = data[16:], 0x00
    while rest:
        chunk, rest = rest[:7], rest[7:]
        last = 0x01 if not rest else 0x00
        unused = 7 - len(chunk)
        reply = _sdo(server, bytes([toggle | unused << 1 | last]) + chunk.ljust(7, b"\x00"))
        assert reply[0] == 0x20 | toggle
        toggle ^= 0x10
    back = slave.sdo.read(0x1A00, 0, complete=True)
    assert back[0] == 5 and struct.unpack_from("<5I", back, 2) == tuple(entries[:5])


def test_mapping_rules_of_coe(slave: CoeSlave) -> None:
    server = SdoServer(slave.node, mailbox_bytes=128)

    def write(index: int, sub: int, value: int, size: int) -> int:
        command = 0x23 | (4 - size) << 2
        reply = _sdo(server, bytes([command]) + struct.pack("<HB", index, sub)
                     + value.to_bytes(size, "little").ljust(4, b"\x00"))  # fmt: skip
        return 0 if reply[0] == 0x60 else struct.unpack_from("<I", reply, 4)[0]

    assert write(0x1600, 1, 0x60410010, 4) == 0x06040043  # sub 0 must be 0 first
    assert write(0x1600, 0, 0, 1) == 0
    assert write(0x1600, 1, 0x60410010, 4) == 0x06040041  # statusword is no output
    assert write(0x1600, 1, 0x60710020, 4) == 0x06040043  # 0x6071 has 16 bits, not 32
    assert write(0x1600, 1, 0x60710010, 4) == 0
    assert write(0x1600, 0, 1, 1) == 0
    assert write(0x1C12, 1, 0x1A00, 2) == 0x06040043  # sub 0 of the assignment is 1
    assert write(0x1C12, 0, 0, 1) == 0
    assert write(0x1C12, 1, 0x1A00, 2) == 0x06090030  # a TxPDO on the outputs
    assert write(0x1C32, 2, 100_000, 4) == 0x06090030  # below the shortest cycle
    assert write(0x1C32, 2, 2_000_000, 4) == 0
    assert slave.device.cycle_s == pytest.approx(2e-3)


def _configure_mailboxes(slave: CoeSlave) -> None:
    for n, (start, control) in enumerate(((0x1000, 0x26), (0x1080, 0x22))):
        slave.esc.write(0x0800 + 8 * n, struct.pack("<HHBBBB", start, 128, control, 0, 1, 0))


def test_pre_op_needs_the_sii_mailboxes(slave: CoeSlave) -> None:
    slave.esc.write(0x0120, b"\x02\x00")
    assert (slave.esc.al_state, slave.esc.al_error, slave.esc.word(0x0134)) == (A.INIT, True, 0x16)
    _configure_mailboxes(slave)
    slave.esc.write(0x0120, b"\x12\x00")  # PRE-OP with the acknowledge
    assert (slave.esc.al_state, slave.esc.al_error, slave.esc.word(0x0134)) == (A.PRE_OP, False, 0)


def test_safe_op_needs_sync_managers_matching_the_pdos(slave: CoeSlave) -> None:
    _configure_mailboxes(slave)
    slave.esc.write(0x0120, b"\x02\x00")
    slave.esc.write(0x0810, struct.pack("<HHBBBB", 0x1100, 8, 0x64, 0, 1, 0))  # 8, not 10 bytes
    slave.esc.write(0x0818, struct.pack("<HHBBBB", 0x1180, 12, 0x20, 0, 1, 0))
    slave.esc.write(0x0120, b"\x04\x00")
    assert (slave.esc.al_state, slave.esc.word(0x0134)) == (A.PRE_OP, 0x001D)
    slave.esc.write(0x0810, struct.pack("<HHBBBB", 0x1100, 10, 0x64, 0, 1, 0))
    slave.esc.write(0x0818, struct.pack("<HHBBBB", 0x1180, 11, 0x20, 0, 1, 0))
    slave.esc.write(0x0120, b"\x14\x00")
    assert (slave.esc.al_state, slave.esc.word(0x0134)) == (A.PRE_OP, 0x001E)
    slave.esc.write(0x0818, struct.pack("<HHBBBB", 0x1180, 12, 0x20, 0, 1, 0))
    slave.esc.write(0x0120, b"\x14\x00")
    assert (slave.esc.al_state, slave.esc.al_error) == (A.SAFE_OP, False)
    slave.esc.write(0x0120, b"\x08\x00")  # OP waits for the first outputs
    assert slave.esc.al_state is A.SAFE_OP and not slave.esc.al_error
    slave.esc.write(0x1100, bytes(10))
    assert slave.esc.al_state is A.OP


def test_dc_synchronous_slave_runs_its_cycle_at_each_sync0_event() -> None:
    """0x1C32:01 = 2 and SYNC0 on, real time: outputs take force and inputs are sampled at the
    SYNC0 events of the slave's DC clock, each at its own instant however late it is handled;
    frames between events only deliver outputs. The clock is driven by hand (ns)."""
    from servobench.sim_backend.physics.plant import Plant, PlantParams

    now = [10**9]
    device = device_from_url("sim://?M=0.1&B=1", clock_mode="real", clock=lambda: now[0] * 1e-9)
    slave = CoeSlave(device, FaultInjector(device, FaultPlan("ethercat")), clock_ns=lambda: now[0])
    esc = slave.esc
    _configure_mailboxes(slave)
    esc.write(0x0120, b"\x02\x00")
    slave.node.set_data(0x6060, 0, b"\x0a")  # CST
    slave.node.set_data(0x1C32, 1, b"\x02\x00")  # DC SYNC0
    slave.node.set_data(0x1A00, 0, b"\x00")  # TxPDO: statusword, position, velocity, torque, 0x10F8
    slave.node.set_data(0x1A00, 5, struct.pack("<I", 0x10F80040))
    slave.node.set_data(0x1A00, 0, b"\x05")
    assert slave.node.get_data(0x1C32, 4) == b"\x07\x00"  # free run, SM2, DC SYNC0 announced
    esc.write(0x0810, struct.pack("<HHBBBB", 0x1100, 10, 0x64, 0, 1, 0))
    esc.write(0x0818, struct.pack("<HHBBBB", 0x1180, 20, 0x20, 0, 1, 0))
    start, cycle = 5_000_000, 1_000_000  # DC system time [ns]: offset 0, local time since t0
    esc.write(0x0990, struct.pack("<Q", start))
    esc.write(0x09A0, struct.pack("<I", cycle))
    esc.write(0x0981, b"\x03")
    esc.write(0x0120, b"\x04\x00")
    assert esc.al_state is A.SAFE_OP and slave.dc_synchronous
    t0 = now[0]  # the ESC's local time 0

    def outputs(cw: int, torque: int) -> None:
        esc.write(0x1100, struct.pack("<Hhih", cw, torque, 0, 0))

    def event(k: int, late_ns: int = 0) -> None:  # the loop gets to event k late_ns late
        now[0] = t0 + start + k * cycle + late_ns
        slave.sync0_due(now[0])

    esc.write(0x0120, b"\x08\x00")
    outputs(0x06, 0)
    assert esc.al_state is A.OP
    for k, cw in enumerate((0x06, 0x07, 0x0F)):
        outputs(cw, 0)
        event(k)
    assert struct.unpack_from("<H", esc.read(0x1180, 2))[0] & 0x6F == 0x27  # enabled
    now[0] = t0 + start + 2 * cycle + 300_000
    outputs(0x0F, 800)  # 0.8 N m (rated 1 N m, per mille), between events 2 and 3
    before = esc.read(0x1180, 20)
    slave.sync0_due(now[0])  # no event due: the inputs stay those of event 2
    assert esc.read(0x1180, 20) == before
    event(3, late_ns=700_000)  # handled 0.7 ms late, taken at its own instant
    event(5, late_ns=100_000)  # event 4 merged into 5: the same outputs in force
    _sw, pos, vel, _torque, stamp = struct.unpack("<HiihQ", esc.read(0x1180, 20))
    assert stamp == start + 5 * cycle  # 0x10F8: the DC system time of the sample, event 5
    plant = Plant(PlantParams(M=0.1, B=1.0))
    plant.hold(0.8, 2 * cycle * 1e-9)  # from event 3 to event 5
    assert vel == pytest.approx(plant.state.v * 1e6, abs=1)  # µrad/s
    assert pos == pytest.approx(plant.state.x * 1e6, abs=1)  # µrad

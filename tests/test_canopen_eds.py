"""The shipped EDS files against independent peers, and the served drive against CiA 301's frames.

* canopen's own EDS parser (``canopen.import_od``) must load every EDS servobench ships.
* ``zeroerr-edriver.eds`` must declare the object set of ZeroErr's published
  EDS for its eDriver (ZeroErr Driver_V1.5.eds): the facts below are copied
  from that file, not from ours.
* SDO frames built by hand from CiA 301 (expedited upload and download, abort)
  go to the served drive as raw CAN frames, and its answers must be the
  bytes CiA 301 prescribes.
"""

from __future__ import annotations

import io
import struct
import time
from importlib import resources

import can
import canopen
import pytest
from canopen.objectdictionary import ODVariable

from servobench.bench.testing.served_canopen import raw_bus, request, served
from servobench.drivers.canopen.link import load_eds, shipped_eds
from servobench.drivers.cia402 import MODE_CSP, MODE_CST, MODE_PROFILE_TORQUE, supports_mode

NODE = 2
SDO_RX, SDO_TX = 0x600 + NODE, 0x580 + NODE

#: From ZeroErr Driver_V1.5.eds: objects the drive has (index, sub) -> (data type, access, PDO).
ZEROERR_HAS = {
    (0x1000, 0): (0x0007, "ro", False),
    (0x1005, 0): (0x0007, "rw", False),
    (0x1006, 0): (0x0007, "rw", False),
    (0x1016, 1): (0x0007, "rw", False),
    (0x1017, 0): (0x0006, "rw", False),
    (0x6040, 0): (0x0006, "rww", True),
    (0x6041, 0): (0x0006, "ro", True),
    (0x6060, 0): (0x0002, "rww", True),
    (0x6061, 0): (0x0002, "ro", True),
    (0x6064, 0): (0x0004, "ro", True),
    (0x606C, 0): (0x0004, "ro", True),
    (0x6071, 0): (0x0003, "rww", True),
    (0x6075, 0): (0x0007, "ro", True),
    (0x6076, 0): (0x0007, "ro", True),
    (0x6077, 0): (0x0003, "ro", True),
    (0x607A, 0): (0x0004, "rww", True),
    (0x60B2, 0): (0x0003, "rww", True),
    (0x60C2, 1): (0x0005, "rww", True),
    (0x60C2, 2): (0x0002, "rww", False),
    (0x6502, 0): (0x0007, "ro", True),
}
#: ... and objects it lacks (issue 10: 0x1013, 0x6007, 0x6072; nor any factor-group object).
ZEROERR_LACKS = (0x1008, 0x100A, 0x1013, 0x6007, 0x605A, 0x6072, 0x608F, 0x6091, 0x6092,
                 0x60A8, 0x60A9)  # fmt: skip


@pytest.mark.parametrize("name", shipped_eds())
def test_canopens_parser_loads_every_shipped_eds(name: str) -> None:
    text = resources.files("servobench.drivers").joinpath(f"data/{name}.eds").read_text("ascii")
    stream = io.StringIO(text)
    stream.name = f"{name}.eds"
    od = canopen.import_od(stream, NODE)
    for index in (0x1000, 0x1001, 0x1018):  # CiA 301's mandatory objects
        assert index in od
    assert od[0x1000].default & 0xFFFF == 402  # a CiA 402 drive
    assert len(od) == len(load_eds(NODE, name))


def test_zeroerr_eds_declares_the_published_object_set() -> None:
    od = load_eds(NODE, "zeroerr-edriver")
    for (index, sub), (data_type, access, pdo) in ZEROERR_HAS.items():
        obj = od[index] if isinstance(od[index], ODVariable) else od[index][sub]
        assert (obj.data_type, obj.access_type, obj.pdo_mappable) == (data_type, access, pdo), hex(
            index
        )
    for index in ZEROERR_LACKS:
        assert index not in od, hex(index)
    assert od[0x1000].default == 0x00420192
    assert [od[0x1018][s].default for s in (1, 2, 3)] == [0x5A65726F, 0x26483052, 0x00020111]
    assert 4 not in od[0x1018]  # no serial number
    modes = od[0x6502].default
    assert modes == 909
    assert all(supports_mode(modes, m) for m in (MODE_PROFILE_TORQUE, MODE_CSP, MODE_CST))
    assert (od[0x60B2].min, od[0x60B2].max) == (-3000, 3000)
    # default PDOs: RPDO1/TPDO1 valid with the controlword / statusword alone, the others invalid
    assert od[0x1400][1].default == 0x202 and od[0x1800][1].default == 0x182
    assert od[0x1401][1].default == 0x80000302 and od[0x1801][1].default == 0x80000282
    assert [od[0x1A01][s].default for s in (0, 1, 2)] == [2, 0x60410010, 0x60640020]


# CiA 301 SDO command specifiers: upload request 0x40; upload response 0x43/0x4B/0x4F (4/2/1
# bytes, expedited, size indicated); download 0x23/0x2B/0x2F (4/2/1 bytes), answered 0x60;
# abort 0x80 + index (LE) + sub-index + abort code (LE).
def _upload(index: int, sub: int) -> bytes:
    return struct.pack("<BHB4x", 0x40, index, sub)


def _download(index: int, sub: int, value: bytes) -> bytes:
    command = {4: 0x23, 2: 0x2B, 1: 0x2F}[len(value)]
    return struct.pack("<BHB", command, index, sub) + value.ljust(4, b"\x00")


def _abort(index: int, sub: int, code: int) -> bytes:
    return struct.pack("<BHBI", 0x80, index, sub, code)


def test_served_zeroerr_answers_cia301_golden_frames() -> None:
    with served(eds="zeroerr-edriver") as (device, url), raw_bus(url) as bus:
        assert request(bus, SDO_RX, _upload(0x1000, 0), SDO_TX) == bytes.fromhex("4300100092014200")
        assert request(bus, SDO_RX, _upload(0x1018, 1), SDO_TX) == bytes.fromhex(
            "43181001"
        ) + bytes.fromhex("6F72655A")
        assert request(bus, SDO_RX, _upload(0x6041, 0), SDO_TX)[:4] == bytes.fromhex("4B416000")
        assert request(bus, SDO_RX, _upload(0x6061, 0), SDO_TX)[:4] == bytes.fromhex("4F616000")
        # what the EDS lacks aborts as a real drive's would: 0x06020000, 0x06090011
        assert request(bus, SDO_RX, _upload(0x6072, 0), SDO_TX) == bytes.fromhex("8072600000000206")
        assert request(bus, SDO_RX, _upload(0x1013, 0), SDO_TX) == bytes.fromhex("8013100000000206")
        assert request(bus, SDO_RX, _download(0x6007, 0, b"\x01\x00"), SDO_TX) == _abort(
            0x6007, 0, 0x06020000
        )
        assert request(bus, SDO_RX, _upload(0x1018, 4), SDO_TX) == bytes.fromhex("8018100411000906")
        # expedited downloads, answered 0x60 + index + sub-index
        assert request(bus, SDO_RX, _download(0x6060, 0, b"\x0a"), SDO_TX) == bytes.fromhex(
            "6060600000000000"
        )
        assert request(bus, SDO_RX, _upload(0x6061, 0), SDO_TX) == bytes.fromhex("4F6160000A000000")
        assert request(
            bus, SDO_RX, _download(0x1006, 0, struct.pack("<I", 500)), SDO_TX
        ) == bytes.fromhex("6006100000000000")
        assert device.cycle_s == pytest.approx(500e-6)
        # 0x1006 is written in PRE-OPERATIONAL only: in OPERATIONAL, 0x08000022
        bus.send(can.Message(arbitration_id=0x000, data=bytes([0x01, NODE]), is_extended_id=False))
        time.sleep(0.05)  # NMT start remote node: OPERATIONAL
        assert request(
            bus, SDO_RX, _download(0x1006, 0, struct.pack("<I", 1000)), SDO_TX
        ) == _abort(0x1006, 0, 0x08000022)
        assert device.cycle_s == pytest.approx(500e-6)

"""The served CiA 402 drive against a master servobench did not write.

The master is canopen's :class:`canopen.BaseNode402` (a ``RemoteNode``) on
python-can's own ``socketcand`` client, with the shipped EDS imported by
canopen itself; it talks to the served drive through the socketcand hub as
any CANopen tool would. What it checks is CiA 301, not servobench's host:

* only the master's heartbeat feeds the drive's heartbeat consumer
  (0x1016; CiA 301 7.2.8.3.2.4): a master whose heartbeat stops while its
  PDOs go on is detected, and the drive faults as 0x6007 = 1 says
  (0x8130, EMCY, torque off);
* in NMT STOPPED the drive answers no SDO (only NMT and error control).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from importlib.resources import files

import canopen
import pytest

from servobench.bench.testing.served_canopen import served
from servobench.drivers.url import parse_drive_url
from servobench.sim_backend.device import WATCHDOG_FAULT, PowerState

EDS = str(files("servobench.drivers") / "data" / "cia402.eds")
NODE = 2
#: The master's own node id: its heartbeat is COB-ID 0x700 + this.
MASTER = 1
#: Heartbeat consumer time the master writes to 0x1016:1 [ms], and its heartbeat period [s].
CONSUMER_MS = 500
HEARTBEAT_S = 0.05
#: Longest wait for the drive to answer or to react, on a loaded machine [s].
ANSWER_S = 5.0
#: Profile torque (0x6060), statusword mask and values (CiA 402).
PROFILE_TORQUE = 4
SW_MASK, SW_ENABLED, SW_FAULT = 0x006F, 0x0027, 0x0008


@contextmanager
def master(url: str) -> Iterator[tuple[canopen.Network, canopen.BaseNode402]]:
    """canopen's CiA 402 master of the served node, on python-can's socketcand client."""
    q = parse_drive_url(url)
    network = canopen.Network()
    network.connect(
        interface="socketcand", channel=q.host, host=q.get_str("host"), port=q.get_int("port")
    )
    try:
        node = canopen.BaseNode402(NODE, canopen.import_od(EDS, NODE))
        network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 1.0  # an answer on a loaded machine; silence is judged by it
        yield network, node
    finally:
        network.disconnect()


def wait_until(condition, what: str) -> None:
    deadline = time.monotonic() + ANSWER_S
    while not condition():
        assert time.monotonic() < deadline, f"{what} within {ANSWER_S} s"
        time.sleep(0.01)


def test_a_master_whose_heartbeat_stops_while_its_pdos_run_is_detected():
    with served() as (device, url), master(url) as (network, node):
        node.nmt.state = "PRE-OPERATIONAL"
        node.sdo[0x6007].raw = 1  # abort connection option: fault
        heartbeat = network.send_periodic(0x700 + MASTER, [0x05], HEARTBEAT_S)
        try:
            node.sdo[0x1016][1].raw = (MASTER << 16) | CONSUMER_MS
            node.rpdo.read()
            rpdo = node.rpdo[1]
            rpdo.clear()
            rpdo.add_variable(0x6040)
            rpdo.add_variable(0x6071)
            rpdo.trans_type = 255
            rpdo.enabled = True
            node.rpdo.save()
            node.sdo[0x6060].raw = PROFILE_TORQUE
            node.nmt.state = "OPERATIONAL"
            for controlword in (0x06, 0x07, 0x0F):  # shut down, switch on, enable operation
                rpdo[0x6040].raw = controlword
                rpdo[0x6071].raw = 0
                rpdo.transmit()
            wait_until(lambda: node.sdo[0x6041].raw & SW_MASK == SW_ENABLED, "operation enabled")
            rpdo.start(0.01)  # the master's PDOs every 10 ms from here on
            time.sleep(3 * CONSUMER_MS / 1000)
            assert device.state is PowerState.ENABLED, "tripped while the heartbeat ran"
        finally:
            heartbeat.stop()
        try:  # the heartbeat stopped, the PDOs go on
            wait_until(lambda: device.state is PowerState.FAULT, "no fault for a silent heartbeat")
            assert device.fault_code == WATCHDOG_FAULT
            assert device.command == 0.0
            wait_until(
                lambda: any(e.code == WATCHDOG_FAULT for e in node.emcy.log), "no EMCY 0x8130"
            )
            assert node.sdo[0x6041].raw & SW_FAULT
            assert node.sdo[0x603F].raw == WATCHDOG_FAULT
        finally:
            rpdo.stop()


def test_no_sdo_is_answered_in_nmt_stopped():
    with served() as (_, url), master(url) as (_, node):
        node.nmt.state = "PRE-OPERATIONAL"
        device_type = node.sdo.upload(0x1000, 0)
        node.nmt.state = "STOPPED"
        with pytest.raises(canopen.SdoCommunicationError):
            node.sdo.upload(0x1000, 0)
        with pytest.raises(canopen.SdoCommunicationError):
            node.sdo.download(0x6060, 0, bytes([PROFILE_TORQUE]))
        node.nmt.state = "PRE-OPERATIONAL"
        assert node.sdo.upload(0x1000, 0) == device_type
        assert node.sdo[0x6060].raw != PROFILE_TORQUE  # the write in STOPPED did nothing

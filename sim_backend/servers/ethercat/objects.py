"""The served EtherCAT slave's object dictionary and the SII description made from it.

The CiA 402 objects are those of the generic EDS the CANopen served drive
serves (``drivers/data/cia402.eds``), so both fieldbuses answer the same
object logic (:mod:`servobench.sim_backend.servers.canopen.drive`). CANopen's
communication objects that CoE has no use for are left out (SYNC and EMCY
COB-IDs 0x1005/0x1014, heartbeat 0x1016/0x1017, the PDO communication
parameters 0x1400/0x1800, the cycle 0x1006: on EtherCAT it is 0x1C32:02),
and CoE's are added (ETG.1000.6 5.6.7.4, ETG.6010):

* 0x1C00 SyncManager communication types (1 mailbox out, 2 mailbox in,
  3 outputs, 4 inputs);
* 0x1C12 / 0x1C13 the PDOs assigned to SM2 / SM3; by default RxPDO 0x1600
  (controlword 0x6040, target torque 0x6071, target position 0x607A,
  torque offset 0x60B2) and TxPDO 0x1A00 (statusword 0x6041, position
  0x6064, velocity 0x606C, torque actual 0x6077), so a generic master
  runs the drive in cyclic synchronous torque without remapping, as the
  default assignment of a real drive's ESI does;
* 0x1C32 / 0x1C33 the SM output / input parameters (synchronisation type,
  cycle time [ns], supported types);
* 0x10F8 the timestamp object (ETG.1000.6 / ETG.1020: UNSIGNED64, ns, read
  only, mappable): the DC system time at which the inputs of the process
  data cycle were sampled.

Without a time stamp (``serve-sim --no-timestamp``, ``timestamp=False``)
the dictionary is that of the shipped EDS ``cia402-nostamp`` (no 0x1013)
and has no 0x10F8: the master has the DC system time of the frame only.
"""

from __future__ import annotations

import canopen
from canopen import objectdictionary as od_types
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from servobench.drivers.canopen.link import load_eds
from servobench.sim_backend.servers.ethercat import sii

#: Objects of the CANopen EDS that CoE has no use for.
CAN_ONLY = (0x1005, 0x1006, 0x1014, 0x1016, 0x1017)
RXPDO_MAP, TXPDO_MAP = 0x1600, 0x1A00
PDOS_PER_DIRECTION = 4
RXPDO_ASSIGN, TXPDO_ASSIGN = 0x1C12, 0x1C13
SM_COMM_TYPE = 0x1C00
SM_OUTPUT_PARAMETER, SM_INPUT_PARAMETER = 0x1C32, 0x1C33
#: The timestamp object: DC system time of the sample [ns] (UNSIGNED64).
TIMESTAMP = 0x10F8
#: The EDS of the drive without a time stamp (no 0x1013).
NO_TIMESTAMP_EDS = "cia402-nostamp"
#: Default mapping: (index, subindex, bits).
DEFAULT_RXPDO = ((0x6040, 0, 16), (0x6071, 0, 16), (0x607A, 0, 32), (0x60B2, 0, 16))
DEFAULT_TXPDO = ((0x6041, 0, 16), (0x6064, 0, 32), (0x606C, 0, 32), (0x6077, 0, 16))
#: 0x1C32:01 synchronisation types: free run, SM2 event, DC SYNC0.
SYNC_FREE_RUN, SYNC_SM, SYNC_DC0 = 0, 1, 2
#: 0x1C32:04 supported types: bit 0 free run, bit 1 SM synchronous, bit 2 DC SYNC0.
SYNC_TYPES_SUPPORTED = 0x0007
#: Shortest cycle the served slave takes [ns].
MIN_CYCLE_NS = 250_000
#: Mailbox buffers (SM0 at 0x1000, SM1 at 0x1080) and process data (SM2, SM3) [bytes].
MAILBOX_OUT, MAILBOX_IN = 0x1000, 0x1080
MAILBOX_BYTES = 128
OUTPUTS_AT, INPUTS_AT = 0x1100, 0x1180
#: CoE details the SII announces (complete access added unless refused).
COE_DETAILS = sii.COE_SDO | sii.COE_SDO_INFO | sii.COE_PDO_ASSIGN | sii.COE_PDO_CONFIG
SM_CONTROL = {1: 0x26, 2: 0x22, 3: 0x64, 4: 0x20}  # mailbox w/r, outputs (watchdog), inputs


def _var(name: str, index: int, sub: int, data_type: int, default: int, access: str = "rw"):
    var = ODVariable(name, index, sub)
    var.data_type, var.access_type, var.default = data_type, access, default
    var.pdo_mappable = False
    return var


def _array(name: str, index: int, data_type: int, values: list[int], access: str = "rw"):
    arr = ODArray(name, index)
    arr.add_member(_var("Number of entries", index, 0, od_types.UNSIGNED8, len(values), access))
    for sub, value in enumerate(values, start=1):
        arr.add_member(_var(f"Entry {sub}", index, sub, data_type, value, access))
    return arr


def _sync_parameter(index: int, cycle_ns: int, supported: int) -> ODRecord:
    rec = ODRecord("SM output parameter" if index == SM_OUTPUT_PARAMETER else
                   "SM input parameter", index)  # fmt: skip
    members = (
        (1, "Synchronization type", od_types.UNSIGNED16, SYNC_FREE_RUN, "rw"),
        (2, "Cycle time", od_types.UNSIGNED32, cycle_ns, "rw"),
        (4, "Synchronization types supported", od_types.UNSIGNED16, supported, "ro"),
        (5, "Minimum cycle time", od_types.UNSIGNED32, MIN_CYCLE_NS, "ro"),
        (6, "Calc and copy time", od_types.UNSIGNED32, 0, "ro"),
        (9, "Delay time", od_types.UNSIGNED32, 0, "ro"),
    )
    rec.add_member(_var("Highest sub-index supported", index, 0, od_types.UNSIGNED8, 9, "ro"))
    for sub, name, kind, default, access in members:
        rec.add_member(_var(name, index, sub, kind, default, access))
    return rec


def _set_mapping(od: canopen.ObjectDictionary, index: int, entries) -> None:
    mapping = od[index]
    for sub in range(1, 9):
        if sub in mapping:
            mapping[sub].default = 0
    mapping[0].default = len(entries)
    for sub, (obj, subindex, bits) in enumerate(entries, start=1):
        mapping[sub].default = obj << 16 | subindex << 8 | bits


def ethercat_od(
    cycle_s: float, timestamp: bool = True, dc_synchronous: bool = True
) -> canopen.ObjectDictionary:
    """The slave's object dictionary (see the module docstring).

    ``timestamp``: 0x1013 and 0x10F8 served; ``dc_synchronous``: 0x1C32:04
    announces DC SYNC0 synchronisation (a lock-step slave does not: it makes
    one cycle of each frame).
    """
    od = load_eds(1) if timestamp else load_eds(1, NO_TIMESTAMP_EDS)
    for index in list(od.indices):
        if index in CAN_ONLY or 0x1400 <= index < 0x1600 or 0x1800 <= index < 0x1A00:
            del od.indices[index]
            od.names.pop(next((n for n, o in od.names.items() if o.index == index), ""), None)
    _set_mapping(od, RXPDO_MAP, DEFAULT_RXPDO)
    _set_mapping(od, TXPDO_MAP, DEFAULT_TXPDO)
    for n in range(1, PDOS_PER_DIRECTION):
        _set_mapping(od, RXPDO_MAP + n, ())
        _set_mapping(od, TXPDO_MAP + n, ())
    od.add_object(_array("Sync manager communication type", SM_COMM_TYPE,
                         od_types.UNSIGNED8, [1, 2, 3, 4], "ro"))  # fmt: skip
    rx = _array("RxPDO assign", RXPDO_ASSIGN, od_types.UNSIGNED16, [RXPDO_MAP, 0, 0, 0])
    rx[0].default = 1
    tx = _array("TxPDO assign", TXPDO_ASSIGN, od_types.UNSIGNED16, [TXPDO_MAP, 0, 0, 0])
    tx[0].default = 1
    od.add_object(rx)
    od.add_object(tx)
    cycle_ns = round(cycle_s * 1e9)
    supported = SYNC_TYPES_SUPPORTED if dc_synchronous else SYNC_TYPES_SUPPORTED & ~0x0004
    od.add_object(_sync_parameter(SM_OUTPUT_PARAMETER, cycle_ns, supported))
    od.add_object(_sync_parameter(SM_INPUT_PARAMETER, cycle_ns, supported))
    if timestamp:
        stamp = _var("Timestamp object", TIMESTAMP, 0, od_types.UNSIGNED64, 0, "ro")
        stamp.pdo_mappable = True
        od.add_object(stamp)
    return od


def _default(od: canopen.ObjectDictionary, index: int, sub: int = 0) -> int:
    obj = od[index]
    var = obj if isinstance(obj, ODVariable) else obj[sub]
    return int(var.default or 0)


def _pdo_specs(od, assign: int, sm: int) -> tuple[sii.PdoSpec, ...]:
    specs = []
    for n in range(1, _default(od, assign) + 1):
        pdo = _default(od, assign, n)
        entries = []
        for sub in range(1, _default(od, pdo) + 1):
            entry = _default(od, pdo, sub)
            index, subindex, bits = entry >> 16, entry >> 8 & 0xFF, entry & 0xFF
            var = od[index] if isinstance(od[index], ODVariable) else od[index][subindex]
            entries.append(sii.PdoEntrySpec(index, subindex, bits, var.data_type, var.name))
        specs.append(sii.PdoSpec(pdo, sm, tuple(entries), od[pdo].name))
    return tuple(specs)


def process_data_bytes(od: canopen.ObjectDictionary, assign: int) -> int:
    """Bytes of the default assignment of ``assign`` (0x1C12 or 0x1C13)."""
    return sum(e.bits for p in _pdo_specs(od, assign, 0) for e in p.entries) // 8


def description(
    od: canopen.ObjectDictionary, serial: int = 1, complete_access: bool = True
) -> sii.SlaveDescription:
    """The SII description of the slave that serves ``od`` (CoE details: complete access or not)."""
    name = str(od[0x1008].default) if 0x1008 in od else "servobench CiA 402 drive"
    out_bytes = process_data_bytes(od, RXPDO_ASSIGN)
    in_bytes = process_data_bytes(od, TXPDO_ASSIGN)
    sms = (
        sii.SyncManagerSpec(MAILBOX_OUT, MAILBOX_BYTES, SM_CONTROL[1], sii.SM_MBX_OUT),
        sii.SyncManagerSpec(MAILBOX_IN, MAILBOX_BYTES, SM_CONTROL[2], sii.SM_MBX_IN),
        sii.SyncManagerSpec(OUTPUTS_AT, out_bytes, SM_CONTROL[3], sii.SM_OUTPUTS),
        sii.SyncManagerSpec(INPUTS_AT, in_bytes, SM_CONTROL[4], sii.SM_INPUTS),
    )
    return sii.SlaveDescription(
        vendor_id=_default(od, 0x1018, 1),
        product_code=_default(od, 0x1018, 2),
        revision=_default(od, 0x1018, 3),
        serial=serial,
        name=name,
        group="servobench drives",
        order="servobench-cia402-ecat",
        sync_managers=sms,
        fmmus=(sii.FMMU_OUTPUTS, sii.FMMU_INPUTS, 0x03),
        txpdos=_pdo_specs(od, TXPDO_ASSIGN, 3),
        rxpdos=_pdo_specs(od, RXPDO_ASSIGN, 2),
        coe_details=COE_DETAILS | (sii.COE_COMPLETE_ACCESS if complete_access else 0),
    )

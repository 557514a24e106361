"""The served drive's Modbus application layer: a request PDU in, a response PDU out.

Follows the MODBUS Application Protocol Specification v1.1b3 (§6 and the
request-processing state diagrams of §6.1-6.21, §7 for exceptions):

* a function the drive does not implement answers exception 01 (illegal
  function): FC01/FC02/FC05/FC15 (the drive has no coils and no discrete
  inputs), FC08 and every undefined code (``41`` -> ``C1 01``);
* then the quantity: outside the function's range (1..125 registers read,
  1..123 written, 1..121 written by FC23) or a byte count that does not
  match it answers 03 (illegal data value), e.g. FC03 with quantity 0 ->
  ``83 03``;
* then the addresses: any register of the range not served answers 02
  (illegal data address), a read-only one written too;
* then the drive executes it; a value it cannot take answers 03, a refused
  action (enable while in fault) 04 (server device failure).

FC43/14 Read Device Identification (§6.21) serves the basic objects
VendorName (0x00), ProductCode (0x01) and MajorMinorRevision (0x02), by
stream (read codes 01-03: the drive has only the basic category, so 02 and
03 answer the basic objects too) or individually (code 04; an unknown
object answers 02); conformity level 0x81 (basic, stream and individual
access). FC17 Report Server ID (§6.17, serial line only) answers the
product name and the run indicator.

:class:`RegisterBridge` turns register access into device calls, as the
served map (:mod:`servobench.drivers.modbus.regmap`) says: every answered request
feeds the watchdog; writes to ``command`` latch it, to ``control`` enable /
disable / quick stop / reset by the map's ``[control]`` values, to
``watchdog`` and ``cycle`` set them; a read that covers ``velocity`` clocks
the drive one cycle (sample at ``t_k``, then the latched command acts),
other feedback reads see the present state. FC23 writes before it reads, so
one FC23 is one lock-step cycle. A ``clock="real"`` device is not clocked:
the read samples the axis as it stands in wall-clock time
(:mod:`servobench.sim_backend.device`), and ``timestamp`` carries the
drive's clock at that instant in whole ticks of the register's ``scale``;
each request is handled at the instant it arrived
(:meth:`~servobench.sim_backend.device.SimulatedDevice.instant`), so an FC23's
command takes force exactly when its feedback is sampled.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence

from servobench import __version__
from servobench.drivers.modbus.regmap import (
    FEEDBACK,
    Register,
    RegisterMap,
    decode,
    encode,
    encode_raw,
    encode_string,
)
from servobench.errors import DriveConfigError, DriveError, UsageError
from servobench.sim_backend.device import DeviceSample, PowerState, SimulatedDevice, clock_counts
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.modbus import ModbusFaultHook
from servobench.sim_backend.faults.spec import FaultPlan

ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4
#: Quantity limits of the register functions (v1.1b3 §6.3, 6.4, 6.12, 6.17).
MAX_READ = 125
MAX_WRITE = 123
MAX_RW_WRITE = 121
#: Identity served when the map has identity registers, and by FC43/14 and FC17.
IDENTITY = {"vendor": "servobench", "product": "simulated DC servo", "firmware": "sim-1"}
#: Read Device Identification conformity level: basic, stream and individual access.
CONFORMITY_BASIC_INDIVIDUAL = 0x81


class ModbusException(Exception):
    """A request the drive answers with exception ``code``."""

    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


class RegisterBridge:
    """Register access of one map, applied to a :class:`SimulatedDevice`.

    ``injector`` counts the clocking reads (from 1) and applies the faults;
    ``hook`` carries out the wire faults.
    """

    def __init__(
        self,
        device: SimulatedDevice,
        regmap: RegisterMap,
        injector: FaultInjector | None = None,
        hook: ModbusFaultHook | None = None,
    ) -> None:
        self.device = device
        self.map = regmap
        self.injector = injector or FaultInjector(device, FaultPlan("modbus-tcp"))
        self.hook = hook or ModbusFaultHook()
        self.regs = sorted(regmap.registers.values(), key=lambda r: (r.kind, r.address))
        for a, b in zip(self.regs, self.regs[1:], strict=False):
            if a.kind == b.kind and b.address < a.end:
                raise DriveConfigError(
                    f"{regmap.path}: registers {a.name!r} and {b.name!r} overlap; cannot serve"
                )
        ctl = regmap.control
        self.control_actions: dict[int, Callable[[], None]] = {}
        for seq, action in (
            (ctl.disable, device.disable),
            (ctl.quick_stop, device.quick_stop),
            (ctl.reset_fault, device.reset_fault),
            (ctl.enable, device.enable),
        ):
            if seq:
                self.control_actions[seq[-1]] = action
        self.control_steps = {
            v for seq in (ctl.enable, ctl.disable, ctl.quick_stop, ctl.reset_fault) for v in seq
        }
        self.words, self.readonly = self._address_space()

    def _address_space(self) -> tuple[dict[tuple[str, int], int], set[tuple[str, int]]]:
        """Served words by (kind, address): map registers, feedback gaps, setup addresses."""
        words: dict[tuple[str, int], int] = {}
        readonly: set[tuple[str, int]] = set()
        for reg in self.regs:
            init = (
                encode_string(reg, IDENTITY.get(reg.name, ""))
                if reg.format == "string"
                else [0] * reg.count
            )
            for i, w in enumerate(init):
                words[(reg.kind, reg.address + i)] = w
                if "w" not in reg.access:
                    readonly.add((reg.kind, reg.address + i))
        for block in self.map.blocks:  # words between feedback registers read as 0
            for addr in range(block.address, block.address + block.count):
                if (block.kind, addr) not in words:
                    words[(block.kind, addr)] = 0
                    readonly.add((block.kind, addr))
        for s in self.map.setup:
            words.setdefault(("holding", s.address), 0)
        return words, readonly

    @property
    def cycles(self) -> int:
        """Clocking reads so far (answered or not)."""
        return self.injector.cycle

    def _overlapping(self, kind: str, address: int, count: int) -> list[Register]:
        return [
            r for r in self.regs if r.kind == kind and r.address < address + count and address < r.end
        ]

    def check(self, kind: str, address: int, count: int, write: bool = False) -> None:
        """Exception 02 unless every register of the range is served (and writable)."""
        for a in range(address, address + count):
            if (kind, a) not in self.words or (write and (kind, a) in self.readonly):
                raise ModbusException(ILLEGAL_ADDRESS)

    # ----------------------------------------------------------------- writes
    def write(self, address: int, values: Sequence[int]) -> None:
        """Write holding registers (already checked); the drive acts on the map's registers."""
        touched = self._overlapping("holding", address, len(values))
        if any(r.address < address or r.end > address + len(values) for r in touched):
            raise ModbusException(ILLEGAL_VALUE)  # half of a 32-bit value
        try:
            for reg in touched:
                self._apply(reg, list(values[reg.address - address : reg.end - address]))
        except DriveError:
            raise ModbusException(DEVICE_FAILURE) from None
        except (UsageError, ValueError):
            raise ModbusException(ILLEGAL_VALUE) from None
        for i, v in enumerate(values):
            self.words[("holding", address + i)] = v

    def _apply(self, reg: Register, words: list[int]) -> None:
        if reg.name == "command":
            self.device.set_command(decode(reg, words))
        elif reg.name == "control":
            code = words[0]
            if code in self.control_actions:
                self.control_actions[code]()
            elif code not in self.control_steps:
                raise ModbusException(ILLEGAL_VALUE)
        elif reg.name == "watchdog":
            timeout_s = decode(reg, words)
            self.device.set_watchdog(timeout_s if timeout_s > 0 else None)
        elif reg.name == "cycle":
            self.device.set_cycle(decode(reg, words))

    # ------------------------------------------------------------------ reads
    def read(self, kind: str, address: int, count: int) -> list[int]:
        """Words of a checked range; a range covering ``velocity`` clocks the drive."""
        touched = [r for r in self._overlapping(kind, address, count) if r.name in FEEDBACK]
        out = [self.words[(kind, a)] for a in range(address, address + count)]
        if not touched:
            return out
        if any(r.name == "velocity" for r in touched):
            refusal = self.hook.before_clock(self.injector.next_cycle())
            if refusal is not None:
                raise ModbusException(refusal)
            sample = self.injector.step()
        else:
            sample = self.injector.sample()
        for reg in touched:
            lo, hi = max(reg.address, address), min(reg.end, address + count)
            words = self._feedback_words(reg, sample)
            out[lo - address : hi - address] = words[lo - reg.address : hi - reg.address]
        return out

    def _feedback_words(self, reg: Register, s: DeviceSample) -> list[int]:
        if reg.name == "velocity":
            return encode(reg, s.velocity)
        if reg.name == "position":
            return encode(reg, s.position)
        if reg.name == "fault":
            return encode_raw(reg, s.fault_code)
        if reg.name == "timestamp":  # the drive clock wraps like a hardware counter
            raw = clock_counts(s.t_s, reg.scale)  # ticks of the register's resolution
            return encode_raw(
                reg, raw % (1 << (16 * reg.count)) if reg.format.startswith("u") else raw
            )
        st = self.map.status
        mask = {
            PowerState.ENABLED: st.enabled,
            PowerState.QUICK_STOP: st.quick_stop,
            PowerState.FAULT: st.fault,
        }.get(s.state)
        return encode_raw(reg, mask or 0)


# ----------------------------------------------------------- function codes
def _registers(words: Sequence[int]) -> bytes:
    return bytes([2 * len(words)]) + b"".join(struct.pack(">H", w) for w in words)


def _need(pdu: bytes, n: int) -> None:
    if len(pdu) < n:
        raise ModbusException(ILLEGAL_VALUE)


class PduHandler:
    """The drive's answer to each request PDU (see the module doc).

    Parameters
    ----------
    bridge : RegisterBridge
        The registers and the device behind them.
    serial_line : bool
        True on RTU: FC17 Report Server ID is a serial-line function.
    """

    def __init__(self, bridge: RegisterBridge, serial_line: bool = False) -> None:
        self.bridge = bridge
        self.serial_line = serial_line
        self._functions: dict[int, Callable[[bytes], bytes]] = {
            0x03: lambda pdu: self._read(pdu, "holding"),
            0x04: lambda pdu: self._read(pdu, "input"),
            0x06: self._write_single,
            0x10: self._write_multiple,
            0x17: self._read_write,
            0x2B: self._encapsulated,
        }
        if serial_line:
            self._functions[0x11] = self._report_server_id

    def handle(self, pdu: bytes) -> bytes:
        """The response PDU: data, or ``fc | 0x80`` and the exception code.

        Raises
        ------
        servobench.sim_backend.faults.modbus.NoAnswer
            An injected fault: the drive sends nothing.
        """
        fc = pdu[0]
        handler = self._functions.get(fc)
        try:
            if handler is None:
                raise ModbusException(ILLEGAL_FUNCTION)
            with self.bridge.device.instant():  # one request, one instant (FC23: write, then read)
                out = handler(pdu)
        except ModbusException as exc:
            return bytes([fc | 0x80, exc.code])
        self.bridge.device.feed()
        return out

    def _read(self, pdu: bytes, kind: str) -> bytes:
        _need(pdu, 5)
        address, count = struct.unpack(">HH", pdu[1:5])
        if not 1 <= count <= MAX_READ:
            raise ModbusException(ILLEGAL_VALUE)
        self.bridge.check(kind, address, count)
        return pdu[:1] + _registers(self.bridge.read(kind, address, count))

    def _write_single(self, pdu: bytes) -> bytes:
        _need(pdu, 5)
        address, value = struct.unpack(">HH", pdu[1:5])
        self.bridge.check("holding", address, 1, write=True)
        self.bridge.write(address, [value])
        return pdu[:5]

    def _write_multiple(self, pdu: bytes) -> bytes:
        _need(pdu, 6)
        address, count, nbytes = struct.unpack(">HHB", pdu[1:6])
        if not (1 <= count <= MAX_WRITE and nbytes == 2 * count and len(pdu) == 6 + nbytes):
            raise ModbusException(ILLEGAL_VALUE)
        self.bridge.check("holding", address, count, write=True)
        self.bridge.write(address, struct.unpack(f">{count}H", pdu[6:]))
        return pdu[:5]

    def _read_write(self, pdu: bytes) -> bytes:
        _need(pdu, 10)
        r_addr, r_count, w_addr, w_count, nbytes = struct.unpack(">HHHHB", pdu[1:10])
        if not (
            1 <= r_count <= MAX_READ
            and 1 <= w_count <= MAX_RW_WRITE
            and nbytes == 2 * w_count
            and len(pdu) == 10 + nbytes
        ):
            raise ModbusException(ILLEGAL_VALUE)
        self.bridge.check("holding", r_addr, r_count)
        self.bridge.check("holding", w_addr, w_count, write=True)
        self.bridge.write(w_addr, struct.unpack(f">{w_count}H", pdu[10:]))  # write first (§6.17)
        return pdu[:1] + _registers(self.bridge.read("holding", r_addr, r_count))

    def _encapsulated(self, pdu: bytes) -> bytes:
        _need(pdu, 2)
        if pdu[1] != 0x0E:  # MEI type: only 14, Read Device Identification
            raise ModbusException(ILLEGAL_FUNCTION)
        _need(pdu, 4)
        code, first = pdu[2], pdu[3]
        objects = [s.encode() for s in device_identity()]
        if code == 4:
            if first >= len(objects):
                raise ModbusException(ILLEGAL_ADDRESS)
            chosen = [first]
        elif code in (1, 2, 3):
            start = first if first < len(objects) else 0  # unknown object: from the start (§6.21)
            chosen = list(range(start, len(objects)))
        else:
            raise ModbusException(ILLEGAL_VALUE)
        body = b"".join(bytes([i, len(objects[i])]) + objects[i] for i in chosen)
        # MEI, code, conformity, more follows = no, next object = 0, number of objects
        return bytes([0x2B, 0x0E, code, CONFORMITY_BASIC_INDIVIDUAL, 0, 0, len(chosen)]) + body

    def _report_server_id(self, pdu: bytes) -> bytes:
        running = 0xFF if self.bridge.device.state is PowerState.ENABLED else 0x00
        data = bytes([0x01, running]) + " ".join(device_identity()).encode()
        return bytes([0x11, len(data)]) + data


def device_identity() -> tuple[str, str, str]:
    """VendorName, ProductCode, MajorMinorRevision of the served drive."""
    return IDENTITY["vendor"], IDENTITY["product"], __version__

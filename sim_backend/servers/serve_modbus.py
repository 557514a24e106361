"""Serve the simulated drive over Modbus TCP or Modbus RTU (a real pymodbus server).

The served register layout is a :mod:`servobench.drivers.regmap` map (``servobench-sim``
unless ``--map`` names another), the same file the client reads. A
:class:`RegisterBridge` turns register access into device calls, through
pymodbus's ``SimDevice(action=...)`` hook, which sees every request that hits
a valid address before the register store answers it:

* every valid request feeds the drive's watchdog (``device.feed()``);
* writes: ``command`` -> ``set_command`` (latched), ``control`` -> enable /
  disable / quick stop / reset fault by the map's ``[control]`` values,
  ``watchdog`` -> ``set_watchdog`` (0 disables), ``cycle`` -> ``set_cycle``;
* reads: a read that covers ``velocity`` clocks the drive one cycle
  (``device.step()``: sample at ``t_k``, then the latched command acts); other
  reads see the current state without clocking (``device.sample()``).

FC23 writes before it reads, so one FC23 is one lock-step cycle. A refused
enable (drive in fault) answers exception 4 (server device failure); an
unknown control value or a partial write of a 32-bit value answers exception 3.

Fault injection (``--fault``, the grammar of :mod:`servobench.sim_backend.faults.spec`;
``N`` counts clocking reads from 1): ``fault@N[:C]``, ``freeze@N``,
``exception@N[:C]`` (``busy@N`` = ``exception@N:6``), ``timeout@N``
(``silence@N``), ``delay@N:MS`` and, on RTU, ``crc@N``; see
:mod:`servobench.sim_backend.faults.modbus`. A refused or unanswered request does not
clock the drive.

RTU runs on a :class:`~servobench.sim_backend.servers.pty_link.PtyLink` that emulates the byte
time of the configured baud rate, so RTU timing measured against the served
drive is that of a real line (without the drive's own turnaround time).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Mapping
from urllib.parse import quote

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from servobench.drivers.regmap import (
    FEEDBACK,
    Register,
    RegisterMap,
    decode,
    encode,
    encode_raw,
    encode_string,
    load_map,
)
from servobench.errors import DriveConfigError, DriveError, UsageError
from servobench.sim_backend.device import DeviceSample, PowerState, SimulatedDevice
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.modbus import ModbusFaultHook
from servobench.sim_backend.faults.spec import FaultPlan, parse_plan
from servobench.sim_backend.servers.pty_link import PtyLink

DEFAULT_MAP = "servobench-sim"
#: Line rate of the served RTU link [bit/s].
DEFAULT_BAUD = 115200
#: How often the serving loop looks at the stop event [s].
STOP_POLL_S = 0.05
#: Modbus RTU inter-frame silence above 19200 baud, fixed by the serial-line spec [s].
T35_FAST_S = 1.75e-3


def rtu_frame_gap_s(baud: int) -> float:
    """Modbus RTU t3.5: 3.5 characters of 11 bits, or 1.75 ms above 19200 baud [s]."""
    return T35_FAST_S if baud > 19200 else 3.5 * 11 / baud


#: Identity strings served when the map has identity registers.
IDENTITY = {"vendor": "servobench", "product": "simulated DC servo", "firmware": "sim-1"}


def parse_faults(spec: str, transport: str = "modbus-tcp") -> FaultPlan:
    """``"fault@50;busy@80"`` as a :class:`~servobench.sim_backend.faults.spec.FaultPlan`."""
    return parse_plan(spec, transport)


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
        self.regs = sorted(regmap.registers.values(), key=lambda r: r.address)
        for a, b in zip(self.regs, self.regs[1:], strict=False):
            if b.address < a.end:  # holding and input share one store here
                raise DriveConfigError(
                    f"{regmap.path}: registers {a.name!r} and {b.name!r} overlap; cannot serve"
                )
        self.control_actions: dict[int, Callable[[], None]] = {}
        ctl = regmap.control
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

    # ----------------------------------------------------------- register store
    def simdata(self) -> list[SimData]:
        """The served address space: every map register, setup address and feedback gap."""
        used: dict[int, tuple[int, bool]] = {}  # address -> (initial word, read-only)
        for reg in self.regs:
            words = (
                encode_string(reg, IDENTITY.get(reg.name, ""))
                if reg.format == "string"
                else [0] * reg.count
            )
            for i, w in enumerate(words):
                used[reg.address + i] = (w, "w" not in reg.access)
        for block in self.map.blocks:  # words between feedback registers read as 0
            for addr in range(block.address, block.address + block.count):
                used.setdefault(addr, (0, True))
        for s in self.map.setup:
            used.setdefault(s.address, (0, False))
        return [
            SimData(addr, values=w, datatype=DataType.REGISTERS, readonly=ro)
            for addr, (w, ro) in sorted(used.items())
        ]

    # ------------------------------------------------------------ action hook
    async def action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus ``SimDevice.action``: called for every request on valid addresses."""
        self.device.feed()
        try:
            if set_values is not None:
                return self._write(address, [int(v) for v in set_values])
            touched = [r for r in self._overlapping(address, count) if r.name in FEEDBACK]
            clocked = any(r.name == "velocity" for r in touched)
            if clocked:
                refusal = await self.hook.before_clock(self.injector.next_cycle())
                if refusal is not None:
                    return refusal
            return self._read(start_address, touched, clocked, registers)
        except DriveError:
            return ExcCodes.DEVICE_FAILURE
        except (UsageError, ValueError):
            return ExcCodes.ILLEGAL_VALUE

    def _overlapping(self, address: int, count: int) -> list[Register]:
        return [r for r in self.regs if r.address < address + count and address < r.end]

    def _write(self, address: int, values: list[int]) -> ExcCodes | None:
        touched = self._overlapping(address, len(values))
        if any(r.address < address or r.end > address + len(values) for r in touched):
            return ExcCodes.ILLEGAL_VALUE  # half of a 32-bit value
        for reg in touched:
            words = values[reg.address - address : reg.end - address]
            if reg.name == "command":
                self.device.set_command(decode(reg, words))
            elif reg.name == "control":
                code = words[0]
                if code in self.control_actions:
                    self.control_actions[code]()
                elif code not in self.control_steps:
                    return ExcCodes.ILLEGAL_VALUE
            elif reg.name == "watchdog":
                timeout_s = decode(reg, words)
                self.device.set_watchdog(timeout_s if timeout_s > 0 else None)
            elif reg.name == "cycle":
                self.device.set_cycle(decode(reg, words))
        return None

    @property
    def cycles(self) -> int:
        """Clocking reads so far (answered or not)."""
        return self.injector.cycle

    def _read(
        self, start_address: int, touched: list[Register], clocked: bool, registers: list[int]
    ) -> ExcCodes | None:
        if not touched:
            return None
        sample = self.injector.step() if clocked else self.injector.sample()
        for reg in touched:
            offset = reg.address - start_address
            registers[offset : offset + reg.count] = self._feedback_words(reg, sample)
        return None

    def _feedback_words(self, reg: Register, s: DeviceSample) -> list[int]:
        if reg.name == "velocity":
            return encode(reg, s.velocity)
        if reg.name == "position":
            return encode(reg, s.position)
        if reg.name == "fault":
            return encode_raw(reg, s.fault_code)
        if reg.name == "timestamp":  # the drive clock wraps like a hardware counter
            raw = int(round(s.t_s / reg.scale))
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


# ---------------------------------------------------------------- serving
def _url_tail(unit: int, map_name: str) -> str:
    return f"unit={unit}&map={quote(map_name, safe='')}"


async def _serve(
    device: SimulatedDevice,
    stop: threading.Event,
    announce: Callable[[str], None],
    options: Mapping[str, str],
    injector: FaultInjector | None,
) -> None:
    map_name = options.get("map") or DEFAULT_MAP
    unit = int(options.get("unit") or 1)
    transport = options.get("transport", "modbus-tcp")
    if transport not in ("modbus-tcp", "modbus-rtu"):
        raise DriveConfigError(f"serve_modbus cannot serve transport {transport!r}")
    if injector is None:
        injector = FaultInjector(device, parse_plan(options.get("fault") or "", transport))
    hook = ModbusFaultHook()
    bridge = RegisterBridge(device, load_map(map_name), injector, hook)
    simdevice = SimDevice(id=unit, simdata=bridge.simdata(), action=bridge.action)
    link: PtyLink | None = None
    if transport == "modbus-tcp":
        host = options.get("host") or "127.0.0.1"
        server = ModbusTcpServer(
            simdevice, address=(host, int(options.get("port") or 0)), ignore_missing_devices=True
        )
        await server.serve_forever(background=True)
        port = server.transport.sockets[0].getsockname()[1]
        url = f"modbus+tcp://{host}:{port}?{_url_tail(unit, map_name)}"
    elif transport == "modbus-rtu":
        baud = int(options.get("baud") or DEFAULT_BAUD)
        link = PtyLink(baud=baud, frame_gap_s=rtu_frame_gap_s(baud)).start()
        hook.link = link
        server = ModbusSerialServer(
            simdevice, port=link.b_path, baudrate=baud, ignore_missing_devices=True
        )
        await server.serve_forever(background=True)
        url = f"modbus+rtu://{link.a_path}?baud={baud}&{_url_tail(unit, map_name)}"
    try:
        announce(url)
        while not stop.is_set():
            await asyncio.sleep(STOP_POLL_S)
    finally:
        await server.shutdown()
        if link is not None:
            link.close()


def serve(
    device: SimulatedDevice,
    stop: threading.Event,
    announce: Callable[[str], None],
    options: Mapping[str, str],
    injector: FaultInjector | None = None,
) -> None:
    """Serve ``device`` (``options["transport"]``: modbus-tcp or modbus-rtu) until ``stop`` is set.

    Faults come from ``injector``, else from ``options["fault"]``.
    """
    asyncio.run(_serve(device, stop, announce, options, injector))

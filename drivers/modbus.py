"""``modbus+tcp://`` and ``modbus+rtu://`` -- a servo drive behind a Modbus register map.

URLs::

    modbus+tcp://HOST:PORT?unit=1&map=NAME
    modbus+rtu:///dev/ttyUSB0?baud=115200&unit=1&map=NAME

``map`` is a shipped register map (``servobench-sim``, ``zlac8015d``) or a
path to a TOML file (:mod:`servobench.drivers.regmap`). Further keys: ``timeout``
(response timeout [s]) and, for RTU, ``parity`` (N, E, O).

One cycle (:meth:`ModbusDrive.exchange`) is one FC23 transaction (write the
command, read the feedback block) when the map says the drive has FC23, else
a write followed by a read. Feedback registers the map scatters over further
blocks are read first, so that against a lock-step drive they too belong to
``t_k``. A missing answer is never retried (the request may have been
executed: a repeated FC23 would apply a command twice, a repeated feedback
read of a lock-step drive would skip a sample), so it is a
:class:`DriveTimeoutError`. The one retry: exception 6 (server device busy)
says the request was *not* executed, so it is sent once more after
:data:`BUSY_RETRY_S` (counted in :attr:`ModbusDrive.retries`); a second
"busy" raises. Every pymodbus result is checked; exception responses become
typed errors (see :func:`exception_error`). Feedback carries the drive's clock when the
map has a ``timestamp`` register (unwrapped), else the host's
``time.monotonic()`` at reception.

Against the lock-step simulated drive every read of the feedback block clocks
the drive one cycle, so :meth:`~servobench.drivers.base.Drive.read` advances it too.
"""

from __future__ import annotations

import logging
import select
import time
from collections.abc import Callable, Sequence
from typing import Any

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from servobench.drivers.base import Drive, DriveInfo, Feedback
from servobench.drivers.regmap import (
    Block,
    Register,
    decode,
    decode_raw,
    decode_string,
    encode,
    encode_raw,
    load_map,
    words_of,
)
from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveError,
    DriveFaultError,
    DriveTimeoutError,
    StateTransitionError,
)

# The library's own log lines would reach stderr through logging's last-resort
# handler; every failure is raised as a typed error here instead. An application
# that configures logging still sees them.
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

#: Response timeout when the URL gives none [s].
DEFAULT_TIMEOUT_S = 0.25
DEFAULT_BAUD = 115200
DEFAULT_TCP_PORT = 502
#: Longest wait for the status register to report "enabled" [s].
ENABLE_TIMEOUT_S = 1.0
ENABLE_POLL_S = 0.005
#: Pause before re-sending a request the drive answered "busy" (exception 6) [s].
BUSY_RETRY_S = 0.001
#: Modbus exception "server device busy": the request was not executed.
EXCEPTION_BUSY = 6

EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    7: "negative acknowledge",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}


def exception_error(code: int, what: str, fault_code: int = 0) -> DriveError:
    """The typed error for a Modbus exception response ``code`` to request ``what``.

    1-3 (the request does not fit the drive: wrong function, address or value)
    -> :class:`DriveConfigError`; 4 (device failure) -> :class:`DriveFaultError`
    carrying ``fault_code``; 5, 6, 11 (busy, no answer behind a gateway) ->
    :class:`DriveTimeoutError`; 10 -> :class:`DriveConnectionError`.
    """
    text = f"{what}: Modbus exception {code} ({EXCEPTION_NAMES.get(code, 'unknown')})"
    if code in (1, 2, 3):
        hint = {1: "the drive lacks this function (fc23 = false in the map?)"}.get(
            code, "the register map does not fit this drive"
        )
        return DriveConfigError(f"{text}: {hint}")
    if code == 4:
        return DriveFaultError(f"{text}, fault register 0x{fault_code:04X}", fault_code)
    if code in (5, 6, 11):
        return DriveTimeoutError(text)
    if code == 10:
        return DriveConnectionError(text)
    return DriveError(text)


class _RtuClient(ModbusSerialClient):
    """The pymodbus serial client, answering reads as soon as bytes arrive.

    The stock ``recv(None)`` polls ``in_waiting`` every millisecond until the
    line has been quiet for one poll, which adds 1-2 ms to every transaction.
    Here it blocks in ``select`` until bytes are there and returns them; the RTU
    framer accumulates partial frames until the CRC closes one.
    """

    def recv(self, size: int | None) -> bytes:
        if size is not None or self.socket is None:
            return super().recv(size)
        try:
            ready, _, _ = select.select(
                [self.socket.fileno()], [], [], self.comm_params.timeout_connect
            )
            if not ready:
                return b""
            return self.socket.read(max(1, self.socket.in_waiting))
        except OSError:
            self.close()
            raise ConnectionException(str(self)) from None


class ModbusDrive(Drive):
    """A servo drive over Modbus TCP or RTU, described by a register map."""

    query_keys = frozenset({"unit", "map", "timeout", "baud", "parity"})

    def __init__(self, url) -> None:
        super().__init__(url)
        u = self.url
        if u.scheme not in ("modbus+tcp", "modbus+rtu"):
            raise DriveConfigError(
                f"ModbusDrive serves modbus+tcp:// and modbus+rtu://, not {u.scheme}://"
            )
        self.rtu = u.scheme == "modbus+rtu"
        map_name = u.get_str("map")
        if not map_name:
            raise DriveConfigError(
                f"{u.scheme}:// needs map=NAME (a shipped register map or a .toml path)"
            )
        self.regmap = load_map(map_name)
        self.units = dict(self.regmap.units)
        self.drive_clock = "timestamp" in self.regmap
        self.unit: int = u.get_int("unit", 1)
        if not 0 <= self.unit <= 255:
            raise DriveConfigError(f"unit={self.unit} is outside 0..255")
        self.timeout_s: float = u.get_float("timeout", DEFAULT_TIMEOUT_S)
        if not self.timeout_s > 0:
            raise DriveConfigError("timeout must be > 0 s")
        if self.rtu:
            if not u.path or u.host:
                raise DriveConfigError(
                    f"modbus+rtu URL needs a device path: modbus+rtu:///dev/ttyUSB0, got {u.raw!r}"
                )
            self.baud: int = u.get_int("baud", DEFAULT_BAUD)
            self.parity = (u.get_str("parity", "N") or "N").upper()
            if self.baud <= 0 or self.parity not in ("N", "E", "O"):
                raise DriveConfigError("baud must be > 0 and parity one of N, E, O")
            self.where = u.path
        else:
            for key in ("baud", "parity"):
                if key in u.query:
                    raise DriveConfigError(f"{key}= is for modbus+rtu://, not modbus+tcp://")
            if not u.host:
                raise DriveConfigError(
                    f"modbus+tcp URL needs a host: modbus+tcp://HOST:PORT, got {u.raw!r}"
                )
            self.where = f"{u.host}:{u.port or DEFAULT_TCP_PORT}"
        self._client: ModbusTcpClient | ModbusSerialClient | None = None
        self._t_offset_s = 0.0
        self._t_last_s: float | None = None
        self._feed_count = 0
        #: Requests re-sent after a "busy" answer since the drive was created.
        self.retries = 0

    def link_recoveries(self) -> dict[str, int]:
        return {"retries": self.retries}

    # ------------------------------------------------------------- transport
    def _open(self) -> None:
        if self.rtu:
            client = _RtuClient(
                self.url.path, baudrate=self.baud, parity=self.parity,
                timeout=self.timeout_s, retries=0, reconnect_delay=0,
            )  # fmt: skip
        else:
            client = ModbusTcpClient(
                self.url.host, port=self.url.port or DEFAULT_TCP_PORT,
                timeout=self.timeout_s, retries=0, reconnect_delay=0,
            )  # fmt: skip
        if not client.connect():
            client.close()
            raise DriveConnectionError(f"cannot connect to Modbus unit {self.unit} at {self.where}")
        self._client = client
        self._t_offset_s, self._t_last_s = 0.0, None
        try:
            self._fault_code()  # the unit answers, and the map's fault register exists
            for s in self.regmap.setup:
                self._call(client.write_register, f"setup write {s.address:#06x}={s.value} ({s.note})",
                           address=s.address, value=s.value)  # fmt: skip
        except BaseException:
            self._close()
            raise

    def _close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def _call(
        self,
        method: Callable[..., ModbusPDU],
        what: str,
        *,
        lookup_fault: bool = True,
        **kwargs: Any,
    ) -> ModbusPDU:
        """Run one pymodbus request; translate every failure into a typed error.

        On exception 4 (device failure) the fault register is read for the error's
        code, unless ``lookup_fault`` is false (the request was that read).
        """
        response = self._request(method, what, **kwargs)
        if response is not None and getattr(response, "exception_code", 0) == EXCEPTION_BUSY:
            time.sleep(BUSY_RETRY_S)  # busy: not executed, so sending it again is safe
            self.retries += 1
            response = self._request(method, what, **kwargs)
        if response is None or response.isError():
            code = getattr(response, "exception_code", 0)
            fault = 0
            if code == 4 and lookup_fault:
                try:
                    fault = self._fault_code()
                except DriveError:
                    fault = 0
            raise exception_error(code, f"{what} at {self.where}", fault)
        return response

    def _request(self, method: Callable[..., ModbusPDU], what: str, **kwargs: Any) -> ModbusPDU:
        """One request, link failures translated; the response is not checked here."""
        if self._client is None:
            raise DriveConnectionError(f"Modbus link to {self.where} is closed")
        try:
            return method(device_id=self.unit, **kwargs)
        except ConnectionException as err:
            raise DriveConnectionError(f"{what}: link to {self.where} lost: {err}") from err
        except ModbusIOException as err:
            raise DriveTimeoutError(
                f"{what}: no answer from unit {self.unit} at {self.where} within {self.timeout_s} s"
            ) from err
        except ModbusException as err:
            raise DriveError(f"{what}: {err}") from err

    def _write(self, reg: Register, words: Sequence[int]) -> None:
        c = self._client
        what = f"write {reg.name} ({reg.address:#06x})"
        if len(words) == 1:
            self._call(c.write_register, what, address=reg.address, value=words[0])
        else:
            self._call(c.write_registers, what, address=reg.address, values=list(words))

    def _read(
        self, kind: str, address: int, count: int, what: str, lookup_fault: bool = True
    ) -> list[int]:
        c = self._client
        method = c.read_holding_registers if kind == "holding" else c.read_input_registers
        rr = self._call(
            method,
            f"read {what} ({address:#06x}+{count})",
            lookup_fault=lookup_fault,
            address=address,
            count=count,
        )
        if len(rr.registers) != count:
            raise DriveError(f"read {what}: asked {count} registers, got {len(rr.registers)}")
        return rr.registers

    def _read_reg(self, reg: Register, lookup_fault: bool = True) -> list[int]:
        return self._read(reg.kind, reg.address, reg.count, reg.name, lookup_fault)

    def _read_block(self, block: Block) -> list[int]:
        return self._read(block.kind, block.address, block.count, "/".join(block.names))

    # ----------------------------------------------------------------- cycles
    def _write_command(self, u: float) -> None:
        self._write(self.regmap["command"], encode(self.regmap["command"], u))

    def _feed(self) -> None:
        if self.regmap.watchdog_feed == "register":
            reg = self.regmap["watchdog_feed"]
            self._feed_count = self._feed_count % 0x7FFF + 1  # 1..32767 fits every format
            self._write(reg, encode_raw(reg, self._feed_count))

    def _cycle(self, primary: Callable[[], list[int]]) -> Feedback:
        """Feed, read the secondary feedback blocks, then ``primary()`` (the read that clocks)."""
        self._feed()
        rest = [self._read_block(b) for b in self.regmap.blocks[1:]]
        return self._decode_feedback([primary(), *rest])

    def _exchange(self, u: float) -> Feedback:
        m = self.regmap
        cmd, fb = m["command"], m.feedback
        words = encode(cmd, u)

        def primary() -> list[int]:
            if not m.fc23:
                self._write(cmd, words)
                return self._read_block(fb)
            rr = self._call(
                self._client.readwrite_registers,
                f"FC23 command/{'/'.join(fb.names)}",
                read_address=fb.address,
                read_count=fb.count,
                write_address=cmd.address,
                values=words,
            )
            if len(rr.registers) != fb.count:
                raise DriveError(f"FC23: asked {fb.count} registers, got {len(rr.registers)}")
            return rr.registers

        return self._cycle(primary)

    def _read_feedback(self) -> Feedback:
        return self._cycle(lambda: self._read_block(self.regmap.feedback))

    def _decode_feedback(self, block_words: list[list[int]]) -> Feedback:
        values: dict[str, list[int]] = {}
        for block, words in zip(self.regmap.blocks, block_words, strict=True):
            for name in block.names:
                values[name] = words_of(block, self.regmap[name], words)
        m = self.regmap
        fault = int(decode_raw(m["fault"], values["fault"]))
        if fault:
            raise DriveFaultError(f"drive at {self.where} reports fault 0x{fault:04X}", fault)
        t_s = self._drive_time(values["timestamp"]) if "timestamp" in values else time.monotonic()
        return Feedback(
            t_s,
            decode(m["velocity"], values["velocity"]),
            decode(m["position"], values["position"]),
            fault,
        )

    def _drive_time(self, words: list[int]) -> float:
        """Drive clock [s], unwrapped across counter roll-over of unsigned timestamps."""
        reg = self.regmap["timestamp"]
        t_s = decode(reg, words)
        if reg.format.startswith("u") and self._t_last_s is not None:
            period_s = (1 << (16 * reg.count)) * reg.scale
            if t_s + self._t_offset_s < self._t_last_s - period_s / 2:
                self._t_offset_s += period_s
        self._t_last_s = t_s + self._t_offset_s
        return self._t_last_s

    # ------------------------------------------------------------ power, setup
    def _control(self, values: Sequence[int]) -> None:
        reg = self.regmap["control"]
        for v in values:
            self._write(reg, encode_raw(reg, v))

    def _status(self) -> int | None:
        if "status" not in self.regmap:
            return None
        return int(decode_raw(self.regmap["status"], self._read_reg(self.regmap["status"])))

    def _enable(self) -> None:
        fault = self._fault_code()
        if fault:
            raise DriveFaultError(
                f"drive at {self.where} is in fault 0x{fault:04X}; reset_fault() first", fault
            )
        self._write_command(0.0)
        self._control(self.regmap.control.enable)
        mask = self.regmap.status.enabled
        if mask is None:
            return
        deadline = time.monotonic() + ENABLE_TIMEOUT_S
        while not (self._status() or 0) & mask:
            if time.monotonic() > deadline:
                fault = self._fault_code()
                if fault:
                    raise DriveFaultError(f"enable refused: fault 0x{fault:04X}", fault)
                raise StateTransitionError(
                    f"drive at {self.where} not enabled after {ENABLE_TIMEOUT_S} s"
                )
            time.sleep(ENABLE_POLL_S)

    def _disable(self) -> None:
        self._control(self.regmap.control.disable)

    def _quick_stop(self) -> None:
        self._write_command(0.0)
        if self.regmap.control.quick_stop:
            self._control(self.regmap.control.quick_stop)

    def _configure_watchdog(self, timeout_s: float) -> None:
        reg = self.regmap["watchdog"]
        self._write(reg, encode(reg, timeout_s))

    def _set_cycle(self, period_s: float) -> None:
        if "cycle" in self.regmap:
            reg = self.regmap["cycle"]
            self._write(reg, encode(reg, period_s))

    # ----------------------------------------------------------------- status
    def _fault_code(self) -> int:
        reg = self.regmap["fault"]
        return int(decode_raw(reg, self._read_reg(reg, lookup_fault=False)))

    def _reset_fault(self) -> None:
        self._control(self.regmap.control.reset_fault)
        fault = self._fault_code()
        if fault:
            raise DriveFaultError(
                f"fault 0x{fault:04X} persists after reset at {self.where}", fault
            )

    def _info(self) -> DriveInfo:
        ident: dict[str, str] = {}
        for name in ("vendor", "product", "firmware", "serial_number"):
            if name in self.regmap:
                reg = self.regmap[name]
                words = self._read_reg(reg)
                ident[name] = (
                    decode_string(reg, words)
                    if reg.format == "string"
                    else str(decode_raw(reg, words))
                )
        status, st = self._status(), self.regmap.status
        state = ""
        if status is not None:
            for label, mask in (
                ("fault", st.fault),
                ("quick_stop", st.quick_stop),
                ("enabled", st.enabled),
            ):
                if mask is not None and status & mask:
                    state = label
                    break
            else:
                state = "disabled"
        return DriveInfo(
            transport=self.url.scheme,
            state=state,
            fault_code=self._fault_code(),
            units=dict(self.units),
            extra={
                "map": self.regmap.name,
                "map_source": self.regmap.source,
                "unit": self.unit,
                "fc23": self.regmap.fc23,
                "link": self.where,
            },  # fmt: skip
            **ident,
        )

"""``modbus+tcp://`` and ``modbus+rtu://`` -- a servo drive behind a Modbus register map.

URLs::

    modbus+tcp://HOST:PORT?unit=1&map=NAME
    modbus+rtu:///dev/ttyUSB0?baud=115200&unit=1&map=NAME

``map`` is a shipped register map (``servobench-sim``, ``zlac8015d``) or a
path to a TOML file (:mod:`servobench.drivers.modbus.regmap`). Further keys: ``timeout``
(response timeout [s]) and, for RTU, ``parity`` (N, E, O). The units of
command, velocity and position are the map's (each register's ``unit``).

One cycle (:meth:`ModbusDrive.exchange`) is one FC23 transaction (write the
command, read the feedback block) when the map says the drive has FC23, else
a write followed by a read. With ``fc23 = "auto"`` FC23 is tried, and a drive
that answers it with exception 1 (illegal function, so nothing was executed)
gets the same cycle as write-then-read, from then on. Feedback registers the
map scatters over further blocks are read first, so that against a lock-step
drive they too belong to ``t_k``. The link (:mod:`servobench.drivers.modbus.link`)
retries nothing but a "busy" answer and turns every failure into a typed
error that says what happened (no answer, a gateway's exception, a drive
fault). Feedback carries the drive's clock when the map has a ``timestamp``
register (unwrapped), else the host's ``time.monotonic()`` midway through
the clocking transaction (request out to answer in; on RTU the frames' wire
time at ``baud`` off both ends). Either way that
midpoint and half the transaction's length are ``Feedback.t_host_s`` and
``Feedback.t_unc_s``.

``open(read_only=True)`` (``commission --dry-run``) only reads: no
``[[setup]]`` write, no watchdog set or fed (``watchdog_feed``), no command
or control write (the base refuses those), so no write function code reaches the drive.

A map whose watchdog is fed by any request (``feed = "any_request"``) over
TCP gets a one-line :class:`~servobench.errors.DriveWarning` at open: a
second client polling the drive (a SCADA, another host) keeps the watchdog
alive even after this host dies. (On an RTU line there is one master.)

:meth:`ModbusDrive.max_rate_hz` is the wire time of the frames of one cycle
(:mod:`servobench.drivers.link_budget`) plus the map's ``turnaround_ms`` per
transaction.

Against the lock-step simulated drive every read of the feedback block clocks
the drive one cycle, so :meth:`~servobench.drivers.base.Drive.read` advances it too.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Sequence

from servobench.drivers.base import Drive, DriveInfo, Feedback
from servobench.drivers.link_budget import modbus_max_rate_hz, modbus_rtu_frames, rtu_gap_s
from servobench.drivers.modbus.link import (  # noqa: F401 (exception_error re-exported)
    EXCEPTION_ILLEGAL_FUNCTION,
    ModbusLink,
    exception_error,
)
from servobench.drivers.modbus.regmap import (
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
    DriveError,
    DriveFaultError,
    SessionWarning,
    StateTransitionError,
    UsageError,
)

#: Response timeout when the URL gives none [s].
DEFAULT_TIMEOUT_S = 0.25
DEFAULT_BAUD = 115200
DEFAULT_TCP_PORT = 502
#: Longest wait for the status register to report "enabled" [s].
ENABLE_TIMEOUT_S = 1.0
ENABLE_POLL_S = 0.005


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
        self.units = self.regmap.signal_units
        self.drive_clock = "timestamp" in self.regmap
        self.unit: int = u.get_int("unit", 1)
        if not 0 <= self.unit <= 255:
            raise DriveConfigError(f"unit={self.unit} is outside 0..255")
        self.timeout_s: float = u.get_float("timeout", DEFAULT_TIMEOUT_S)
        if not self.timeout_s > 0:
            raise DriveConfigError("timeout must be > 0 s")
        self.baud = 0  #: RTU line speed [bit/s]; 0 on TCP
        if self.rtu:
            if not u.path or u.host:
                raise DriveConfigError(
                    f"modbus+rtu URL needs a device path: modbus+rtu:///dev/ttyUSB0, got {u.raw!r}"
                )
            self.baud = u.get_int("baud", DEFAULT_BAUD)
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
        self.link = ModbusLink(
            self.unit,
            self.timeout_s,
            rtu=(u.path, self.baud, self.parity) if self.rtu else None,
            tcp=None if self.rtu else (u.host, u.port or DEFAULT_TCP_PORT),
        )
        self.link.fault_lookup = self._fault_code
        #: FC23 in use: the map's choice until an "auto" map's drive refuses it.
        self.fc23 = self.regmap.fc23
        self._t_offset_s = 0.0
        self._t_last_s: float | None = None
        self._feed_count = 0
        self._sent = 0.0  # host clock as the clocking request went out [s]

    @property
    def retries(self) -> int:
        """Requests re-sent after a "busy" answer since the drive was created."""
        return self.link.retries

    def link_recoveries(self) -> dict[str, int]:
        return {"retries": self.retries}

    def max_rate_hz(self) -> float:
        """Wire time of one cycle's frames plus the map's turnaround per transaction.

        An ``fc23 = "auto"`` map is costed as write-then-read, the slower of the two.
        """
        m = self.regmap
        fc23 = m.fc23 and not m.fc23_auto
        frames = modbus_rtu_frames(m["command"].count, m.feedback.count, fc23)
        transactions = list(zip(frames[::2], frames[1::2], strict=True))
        transactions += [(8, 5 + 2 * b.count) for b in m.blocks[1:]]
        if m.watchdog_feed == "register":
            transactions.append((8, 8) if m["watchdog_feed"].count == 1 else (11, 8))
        return modbus_max_rate_hz(
            transactions, rtu=self.rtu, baud=self.baud, turnaround_s=m.turnaround_s
        )

    def rate_limit_reason(self) -> str:
        """How many transactions one cycle takes, when the map spreads them."""
        m = self.regmap
        reads = len(m.blocks)
        extra = [f"{reads} feedback reads per cycle (map {m.name!r}: its registers are not adjacent)"] if reads > 1 else []
        if "timestamp" not in m:
            extra.append("no time-stamp register")
        if m.watchdog_feed == "register":
            extra.append("a watchdog feed write per cycle")
        return ", ".join(extra)

    def log_metadata(self) -> dict[str, str]:
        meta = super().log_metadata()
        meta["modbus_map"] = self.regmap.name
        if self.regmap.fc23_auto:
            meta["fc23"] = "yes" if self.fc23 else "no (the drive answered exception 1)"
        return meta

    # ------------------------------------------------------------- transport
    def _open(self) -> None:
        self.link.connect()
        self.fc23 = self.regmap.fc23
        self._t_offset_s, self._t_last_s = 0.0, None
        try:
            self._fault_code()  # the unit answers, and the map's fault register exists
            for s in () if self.read_only else self.regmap.setup:
                self._call("write_register", f"setup write {s.address:#06x}={s.value} ({s.note})",
                           address=s.address, value=s.value)  # fmt: skip
        except BaseException:
            self._close()
            raise
        if not self.rtu and not self.read_only and self.regmap.watchdog_feed == "any_request":
            warnings.warn(
                SessionWarning(
                    f"{self.where}: map {self.regmap.name!r} feeds the drive's watchdog with any "
                    "request, so another Modbus client polling this drive keeps the watchdog "
                    "alive even if this host dies; use a watchdog feed register "
                    '(feed = "register") where the drive has one'
                ),
                stacklevel=3,
            )

    def _close(self) -> None:
        self.link.close()

    def _call(self, method: str, what: str, **kwargs):
        return self.link.call(method, what, **kwargs)

    def _write(self, reg: Register, words: Sequence[int]) -> None:
        what = f"write {reg.name} ({reg.address:#06x})"
        if self.read_only:  # the last guard: nothing above should have come here
            raise UsageError(f"{self.where} was opened read-only: refused to {what}")
        if len(words) == 1:
            self._call("write_register", what, address=reg.address, value=words[0])
        else:
            self._call("write_registers", what, address=reg.address, values=list(words))

    def _read(
        self, kind: str, address: int, count: int, what: str, lookup_fault: bool = True
    ) -> list[int]:
        method = "read_holding_registers" if kind == "holding" else "read_input_registers"
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
        if self.regmap.watchdog_feed == "register" and not self.read_only:  # none armed read-only
            reg = self.regmap["watchdog_feed"]
            self._feed_count = self._feed_count % 0x7FFF + 1  # 1..32767 fits every format
            self._write(reg, encode_raw(reg, self._feed_count))

    def _cycle(self, primary: Callable[[], list[int]]) -> Feedback:
        """Feed, read the secondary feedback blocks, then ``primary()`` (the read that clocks)."""
        self._feed()
        rest = [self._read_block(b) for b in self.regmap.blocks[1:]]
        words = primary()
        return self._decode_feedback([words, *rest], self._sample_window(self._sent, time.monotonic()))

    def _sample_window(self, sent: float, received: float) -> tuple[float, float]:
        """Host instants [s] between which the drive sampled during the clocking transaction.

        On an RTU line the request cannot be handled before its last byte
        arrived and t3.5 of silence ended it, nor the answer leave after its
        first byte had to: the frames' wire time at ``baud`` comes off both ends (8 data bits, start, stop and
        the parity bit where there is one). Over TCP, or a port faster than
        its baud rate, the whole transaction.
        """
        if not self.rtu:
            return sent, received
        m = self.regmap
        request, answer = modbus_rtu_frames(m["command"].count, m.feedback.count, self.fc23)[-2:]
        # (FC23, or the read after the write: the clocking transaction alone is bracketed)
        char_s = (10 if self.parity == "N" else 11) / self.baud
        # the slave knows the request ended only after t3.5 of silence
        lo, hi = sent + request * char_s + rtu_gap_s(self.baud), received - answer * char_s
        return (lo, hi) if lo < hi else (sent, received)

    def _exchange(self, u: float) -> Feedback:
        m = self.regmap
        cmd, fb = m["command"], m.feedback
        words = encode(cmd, u)

        def primary() -> list[int]:
            if self.fc23:
                self._sent = time.monotonic()
                registers = self._fc23(words)
                if registers is not None:
                    return registers
                self.fc23 = False  # exception 1: not executed; write, then read, from now on
            self._write(cmd, words)
            self._sent = time.monotonic()
            return self._read_block(fb)

        return self._cycle(primary)

    def _fc23(self, words: list[int]) -> list[int] | None:
        """One FC23 transaction: write the command, read the feedback block.

        None when an ``fc23 = "auto"`` map's drive answers exception 1 (it lacks FC23).
        """
        cmd, fb = self.regmap["command"], self.regmap.feedback
        auto = frozenset({EXCEPTION_ILLEGAL_FUNCTION}) if self.regmap.fc23_auto else frozenset()
        rr = self._call(
            "readwrite_registers",
            f"FC23 command/{'/'.join(fb.names)}",
            accept=auto,
            read_address=fb.address,
            read_count=fb.count,
            write_address=cmd.address,
            values=words,
        )
        if rr.isError():
            return None
        if len(rr.registers) != fb.count:
            raise DriveError(f"FC23: asked {fb.count} registers, got {len(rr.registers)}")
        return rr.registers

    def _read_feedback(self) -> Feedback:
        def primary() -> list[int]:
            self._sent = time.monotonic()
            return self._read_block(self.regmap.feedback)

        return self._cycle(primary)

    def _decode_feedback(
        self, block_words: list[list[int]], bracket: tuple[float, float]
    ) -> Feedback:
        values: dict[str, list[int]] = {}
        for block, words in zip(self.regmap.blocks, block_words, strict=True):
            for name in block.names:
                values[name] = words_of(block, self.regmap[name], words)
        m = self.regmap
        fault = int(decode_raw(m["fault"], values["fault"]))
        if fault:
            raise DriveFaultError(f"drive at {self.where} reports fault 0x{fault:04X}", fault)
        t_host_s, t_unc_s = 0.5 * (bracket[0] + bracket[1]), 0.5 * (bracket[1] - bracket[0])
        t_s = self._drive_time(values["timestamp"]) if "timestamp" in values else t_host_s
        return Feedback(
            t_s,
            decode(m["velocity"], values["velocity"]),
            decode(m["position"], values["position"]),
            fault,
            t_host_s=t_host_s,
            t_unc_s=t_unc_s,
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

    def _device_identification(self) -> dict[str, str]:
        """Vendor, product and revision by FC43/14 (basic objects 0-2); empty if the drive has none."""
        try:
            rr = self._call(
                "read_device_information", "read device identification (FC43/14)", read_code=1
            )
        except (DriveConfigError, DriveFaultError):
            return {}
        info = getattr(rr, "information", {}) or {}
        names = {0: "vendor", 1: "product", 2: "firmware"}
        return {
            names[k]: (v.decode(errors="replace") if isinstance(v, bytes) else str(v))
            for k, v in info.items()
            if k in names
        }

    def _info(self) -> DriveInfo:
        ident: dict[str, str] = {}
        if not any(name in self.regmap for name in ("vendor", "product", "firmware")):
            ident = self._device_identification()
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
                "fc23": self.fc23,
                "link": self.where,
                "max_rate_hz": self.max_rate_hz(),
            },  # fmt: skip
            **ident,
        )

"""The EtherCAT master of the ``ethercat://`` drive: pysoem (SOEM) session and cycle.

:class:`EthercatMaster` owns everything pysoem does for the drive, and turns
pysoem's exceptions into servobench's typed errors at this boundary:

* bring-up in PRE-OP: scan (``config_init``), the slave at position
  ``slave``, its identity (SII and 0x1018), the CiA 402 check (0x1000 device
  profile 402, 0x6502 modes), SDO access with typed errors;
* the PDO mapping (:mod:`.layout`): 0x1C12/0x1C13 and 0x1600/0x1A00 written
  by complete access and read back entry by entry; where the slave refuses
  complete access or stores it wrongly, written entry by entry and read back
  again (and SOEM told not to read the mapping by complete access either);
  then ``config_map`` and a check of the sizes the slave took;
* optional objects (:meth:`EthercatMaster.sdo_write_optional`): read first,
  written only where they differ, a refusal returned as a remark, not raised;
* every pysoem exception (``SdoError``, ``ConfigMapError`` with its list,
  ``PacketError``, ``MailboxError``, ``WkcError`` ...) turned into one line
  naming the slave, the object and the abort code with its CiA 301 text
  (:func:`describe_soem_error`);
* PRE-OP -> SAFE-OP -> OP with DC SYNC0 (``config_dc``, ``dc_sync``) where the
  slave has distributed clocks, and 0x1C32:01 = 2 (DC-synchronous: the slave
  takes the outputs and samples the inputs at each SYNC0 event) where
  0x1C32:04 announces it; the SYNC0 grid (start 0x0990, cycle 0x09A0) is
  read back; back to PRE-OP for a new cycle period;
* the cycle: outputs out, inputs and the DC system time back in one frame
  (LRW + FRMW), the working counter checked: a frame lost, late or with a
  wrong working counter is counted and sent again (a lock-step slave that
  did see it has then run one cycle more, which its time stamp shows), and
  ``max_wkc_errors`` of them in a row raise
  :class:`~servobench.errors.DriveConnectionError` (the slave's SM watchdog
  stops the axis on its side);
* the SM watchdog (0x0400/0x0420 through pysoem's ``set_watchdog``): armed,
  and disarmed (time 0) at close, when the slave also goes to INIT;
* a keep-alive thread that sends the present outputs while the host is idle
  and the axis is *not* enabled, so the slave stays in OP between runs; while
  the axis is enabled only the host's own cycles feed the SM watchdog, so a
  host that stalls has the axis stopped within the watchdog.

Emergencies (CoE EMCY) are collected by a callback; the last one is kept.
"""

from __future__ import annotations

import contextlib
import struct
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from servobench.drivers.ethercat.layout import (
    REQUIRED_RX,
    REQUIRED_TX,
    RX_OBJECTS,
    TIMESTAMPS,
    TX_OBJECTS,
    PdoLayout,
)
from servobench.drivers.ethercat.options import EthercatOptions
from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveError,
    DriveTimeoutError,
    DriveUnavailableError,
    StateTransitionError,
)

INIT, PRE_OP, SAFE_OP, OP = 0x01, 0x02, 0x04, 0x08
AL_ACK = 0x10
#: AL status code of an expired SM watchdog (ETG.1000.6, table 11).
AL_SM_WATCHDOG = 0x001B
#: Aborts that mean "no such object / subindex".
ABSENT = (0x06020000, 0x06090011)
#: Longest wait for an AL state [s] (a drive may take a while into SAFE-OP).
STATE_TIMEOUT_S = 3.0
#: Largest idle time before the keep-alive sends a frame [s].
KEEPALIVE_S = 0.02
#: SOEM's timeouts [µs]: "the slave answered" on a loaded host (SOEM's defaults, 2 ms for a
#: register access and 20 ms for the scan, suit a slave controller answering in microseconds).
SOEM_TIMEOUTS_US = {"ret": 20_000, "safe": 200_000, "eeprom": 200_000}
#: Scans before "no slave" (a slave may miss one while its host is busy).
SCANS = 3
RX_ASSIGN, TX_ASSIGN, RX_MAP, TX_MAP = 0x1C12, 0x1C13, 0x1600, 0x1A00
#: 0x1C32:01 synchronisation type DC SYNC0 (ETG.1020).
SYNC_DC0 = 2


#: CiA 301 texts of the SDO abort codes (SOEM's own text is used where it gives one).
ABORT_TEXTS = {
    0x05030000: "Toggle bit not alternated",
    0x05040000: "SDO protocol timed out",
    0x05040001: "Client/server command specifier not valid or unknown",
    0x06010000: "Unsupported access to an object",
    0x06010001: "Attempt to read a write only object",
    0x06010002: "Attempt to write a read only object",
    0x06020000: "Object does not exist in the object dictionary",
    0x06040041: "Object cannot be mapped to the PDO",
    0x06040042: "The number and length of the objects to be mapped would exceed PDO length",
    0x06040043: "General parameter incompatibility reason",
    0x06070010: "Data type does not match, length of service parameter does not match",
    0x06090011: "Sub-index does not exist",
    0x06090030: "Value range of parameter exceeded",
    0x08000000: "General error",
    0x08000020: "Data cannot be transferred or stored to the application",
    0x08000021: "Data cannot be transferred or stored to the application because of local control",
    0x08000022: "Data cannot be transferred or stored to the application because of the present device state",
}
#: SOEM's packet errors (an answer that is not the one asked for).
PACKET_ERRORS = {1: "unexpected frame returned", 3: "data container too small for type"}


def abort_text(code: int, soem_text: str = "") -> str:
    """``0x06010002 (Attempt to write a read only object)``."""
    text = soem_text.strip() or ABORT_TEXTS.get(code, "unknown abort code")
    return f"0x{code:08X} ({text})"


def describe_soem_error(err: BaseException) -> str:
    """One phrase for any pysoem exception: the object and abort code where it names them."""
    name = type(err).__name__
    if name == "SdoError":
        return (f"SDO 0x{err.index:04X}:{err.subindex} aborted "
                f"{abort_text(err.abort_code, getattr(err, 'desc', '') or '')}")  # fmt: skip
    if name == "ConfigMapError":
        return "; ".join(describe_soem_error(e) for e in err.error_list) or "no detail"
    if name == "PacketError":
        code = getattr(err, "error_code", 0)
        return f"mailbox answer not the one asked for (SOEM packet error {code}: {PACKET_ERRORS.get(code, 'unknown')})"
    if name == "MailboxError":
        return f"mailbox error {getattr(err, 'error_code', 0)} ({getattr(err, 'desc', '')})"
    if name == "WkcError":
        return "no answer (wrong working counter)"
    detail = getattr(err, "message", None) or str(err) or repr(err)
    return f"{name}: {detail}"


def import_pysoem():
    """pysoem, or one line saying what to install."""
    try:
        import pysoem
    except ImportError:
        raise DriveUnavailableError(
            "ethercat:// needs pysoem (the SOEM EtherCAT master): "
            "pip install 'servobench[ethercat]' (or: pip install pysoem)"
        ) from None
    for name, value in SOEM_TIMEOUTS_US.items():
        if getattr(pysoem.settings.timeouts, name) < value:
            setattr(pysoem.settings.timeouts, name, value)
    return pysoem


class EthercatMaster:
    """One slave on one interface, driven by SOEM (see the module docstring)."""

    def __init__(self, options: EthercatOptions) -> None:
        self.options = options
        self.pysoem = import_pysoem()
        self.master: Any = None
        self.slave: Any = None
        self.rx: PdoLayout | None = None
        self.tx: PdoLayout | None = None
        self.has_dc = False
        #: The slave runs its process data cycle at SYNC0 (0x1C32:01 = 2 taken).
        self.dc_synchronous = False
        #: ``(start, cycle)`` of SYNC0 [ns of DC system time] while it is on.
        self.sync0 = (0, 1)
        self.complete_access = True
        #: Why the mapping went entry by entry ("" while complete access held).
        self.complete_access_note = ""
        self.wkc_errors = 0  #: cycles with a wrong working counter or no frame, since open
        self.emergency: tuple[int, int] | None = None
        self.outputs = b""
        self._lock = threading.Lock()
        self._last_cycle = 0.0
        self._keepalive: threading.Thread | None = None
        self._stop = threading.Event()
        self.keep_alive = False  #: the keep-alive may send (the axis is not enabled)
        self.keepalive_error: BaseException | None = None

    @property
    def name(self) -> str:
        return f"EtherCAT slave {self.options.slave} on {self.options.iface}"

    # ------------------------------------------------------------ bring-up
    def open(self) -> None:
        """Scan and pick the slave; it is in PRE-OP afterwards."""
        o = self.options
        master = self.pysoem.Master()
        try:
            master.open(o.iface)
        except Exception as err:  # pysoem raises ConnectionError and others, by version
            raise DriveConnectionError(
                f"cannot open EtherCAT interface {o.iface!r}: {err} (raw sockets need CAP_NET_RAW)"
            ) from None
        self.master = master
        for _ in range(SCANS):
            with self.translated("scan (config_init)"):
                found = master.config_init()
            if found >= o.slave:
                break
        if found < o.slave:
            self.close_socket()
            raise DriveConnectionError(
                f"no EtherCAT slave {o.slave} on {o.iface}: {max(found, 0)} slave(s) found"
            )
        self.slave = master.slaves[o.slave - 1]
        self.slave.add_emergency_callback(self._on_emergency)
        self.wait_state(PRE_OP)

    def _on_emergency(self, emcy: Any) -> None:
        self.emergency = (int(emcy.error_code), int(emcy.error_reg))

    def identity(self) -> dict[str, Any]:
        s = self.slave
        return {"name": s.name, "vendor": s.man, "product": s.id, "revision": s.rev}

    def close_socket(self) -> None:
        if self.master is not None:
            self.master.close()
            self.master = None

    @contextlib.contextmanager
    def translated(self, what: str) -> Iterator[None]:
        """Any pysoem exception during ``what`` as one :class:`DriveError` line naming the slave."""
        p = self.pysoem
        try:
            yield
        except DriveError:
            raise
        except p.SdoError as err:
            error = DriveConfigError(f"{self.name}: {what}: {describe_soem_error(err)}")
            error.abort_code = err.abort_code
            raise error from None
        except p.ConfigMapError as err:
            error = DriveConfigError(f"{self.name}: {what}: {describe_soem_error(err)}")
            codes = [e.abort_code for e in err.error_list if type(e).__name__ == "SdoError"]
            error.abort_code = codes[0] if codes else None
            raise error from None
        except (p.PacketError, p.MailboxError) as err:  # the slave answered, but not as asked
            raise DriveConfigError(f"{self.name}: {what}: {describe_soem_error(err)}") from None
        except p.WkcError as err:
            raise DriveTimeoutError(f"{self.name}: {what}: {describe_soem_error(err)}") from None
        except Exception as err:  # pysoem's other exceptions (SdoInfoError, EepromError, ...)
            raise DriveError(f"{self.name}: {what}: {describe_soem_error(err)}") from None

    # ----------------------------------------------------------------- SDO
    def sdo_read(self, index: int, sub: int, fmt: str) -> Any:
        data = self._sdo(lambda: self.slave.sdo_read(index, sub), index, sub, "read")
        try:
            return struct.unpack_from("<" + fmt, data)[0]
        except struct.error:
            raise DriveConfigError(
                f"{self.name}: 0x{index:04X}:{sub} answered {len(data)} bytes, not '{fmt}'"
            ) from None

    def sdo_optional(self, index: int, sub: int, fmt: str) -> Any:
        """``None`` when the slave has no such object (abort 0x06020000 / 0x06090011)."""
        try:
            return self.sdo_read(index, sub, fmt)
        except DriveConfigError as err:
            if getattr(err, "abort_code", None) in ABSENT:
                return None
            raise

    def sdo_write(self, index: int, sub: int, data: bytes, ca: bool = False) -> None:
        what = "write" + (" (complete access)" if ca else "")
        self._sdo(lambda: self.slave.sdo_write(index, sub, data, ca=ca), index, sub, what)

    def sdo_write_optional(self, index: int, sub: int, fmt: str, value: int) -> str | None:
        """Write an object the run can do without: read it first, write only where it
        differs. ``None`` when it holds ``value`` now (or the slave has no such object);
        else the refusal as a remark (read-only, or refused otherwise: abort
        0x06010002 and the like). A slave that does not answer at all still raises."""
        try:
            present = self.sdo_read(index, sub, fmt)
        except DriveConfigError as err:
            if getattr(err, "abort_code", None) in ABSENT:
                return None  # nothing to set
            present = None  # unreadable (write-only): try the write
        if present == value:
            return None
        try:
            self.sdo_write(index, sub, struct.pack("<" + fmt, value))
        except DriveConfigError as err:
            kept = "" if present is None else f", left at {present}"
            return f"0x{index:04X}:{sub} = {value} refused ({str(err).split(': ', 1)[-1]}){kept}"
        return None

    def _sdo(self, call: Callable[[], Any], index: int, sub: int, what: str) -> Any:
        with self._lock, self.translated(f"SDO {what} 0x{index:04X}:{sub}"):
            return call()

    # ------------------------------------------------------------- mapping
    def plan_pdos(
        self, rx_present: list[int], tx_present: list[int], required_rx: tuple[int, ...] = REQUIRED_RX,
    ) -> None:  # fmt: skip
        """The layouts of the objects the slave has (nothing written: a read-only open)."""
        rx = PdoLayout.choose(RX_OBJECTS, rx_present)
        tx = PdoLayout.choose(TX_OBJECTS, tx_present)
        for layout, required in ((rx, required_rx), (tx, REQUIRED_TX)):
            missing = [f"0x{i:04X}" for i in required if not layout.has(i)]
            if missing:
                raise DriveConfigError(f"{self.name} lacks {', '.join(missing)}: no CiA 402 drive")
        self.rx, self.tx = rx, tx

    def map_pdos(
        self, rx_present: list[int], tx_present: list[int], required_rx: tuple[int, ...] = REQUIRED_RX,
    ) -> None:  # fmt: skip
        """Write the mapping (complete access first, read back), then let SOEM map it."""
        self.plan_pdos(rx_present, tx_present, required_rx)
        rx, tx = self.rx, self.tx
        self._install(RX_ASSIGN, RX_MAP, rx.entries())
        try:
            self._install(TX_ASSIGN, TX_MAP, tx.entries())
        except DriveConfigError:
            if not any(tx.has(i) for i in TIMESTAMPS):
                raise
            tx = PdoLayout(tuple(o for o in tx.objects if o[0] not in TIMESTAMPS))  # not mappable
            self._install(TX_ASSIGN, TX_MAP, tx.entries())
        self.rx, self.tx = rx, tx
        if self.complete_access and not self._reads_by_complete_access(rx, tx):
            self.complete_access = False
            self.complete_access_note = "refused on reading: mapped entry by entry"
        if not self.complete_access:  # nor may SOEM read the mapping by complete access
            with self._lock:
                self.slave._disable_complete_access()
        with self._lock, self.translated("PDO mapping (SOEM config_map)"):
            self.master.config_map()
        got = (len(self.slave.output), len(self.slave.input))
        if got != (rx.size, tx.size):
            raise DriveConfigError(
                f"{self.name} mapped {got[0]}/{got[1]} output/input bytes, not {rx.size}/{tx.size}"
            )
        self.outputs = bytes(rx.size)

    def _install(self, assign: int, pdo: int, entries: list[int]) -> None:
        """One PDO and its assignment: by complete access where the slave takes it and stores
        it as sent, else entry by entry (CiA 301's way); read back either way."""
        if self.complete_access:
            try:
                self.sdo_write(assign, 0, struct.pack("<BxH", 1, pdo), ca=True)
                self.sdo_write(pdo, 0, struct.pack(f"<Bx{len(entries)}I", len(entries), *entries),
                               ca=True)  # fmt: skip
            except DriveConfigError:
                self.complete_access = False
                self.complete_access_note = "refused: mapped entry by entry"
            else:
                stored = self._stored(assign, pdo)
                if stored == ([pdo], entries):
                    return
                self.complete_access = False
                self.complete_access_note = (
                    f"stored wrongly (0x{assign:04X}/0x{pdo:04X} read back {_mapping_text(*stored)}): "
                    "mapped entry by entry"
                )
        self.sdo_write(assign, 0, b"\x00")
        self.sdo_write(pdo, 0, b"\x00")
        for sub, entry in enumerate(entries, start=1):
            self.sdo_write(pdo, sub, struct.pack("<I", entry))
        self.sdo_write(pdo, 0, bytes([len(entries)]))
        self.sdo_write(assign, 1, struct.pack("<H", pdo))
        self.sdo_write(assign, 0, b"\x01")
        stored = self._stored(assign, pdo)
        if stored != ([pdo], entries):
            raise DriveConfigError(
                f"{self.name}: PDO mapping 0x{assign:04X}/0x{pdo:04X} reads back "
                f"{_mapping_text(*stored)} after writing {_mapping_text([pdo], entries)} entry by entry"
            )

    def _stored(self, assign: int, pdo: int) -> tuple[list[int], list[int]]:
        """What the slave holds: the PDOs assigned, the entries of ``pdo`` (read entry by entry)."""
        assigned = [self.sdo_read(assign, sub, "H")
                    for sub in range(1, self.sdo_read(assign, 0, "B") + 1)]  # fmt: skip
        entries = [self.sdo_read(pdo, sub, "I") for sub in range(1, self.sdo_read(pdo, 0, "B") + 1)]
        return assigned, entries

    def _reads_by_complete_access(self, rx: PdoLayout, tx: PdoLayout) -> bool:
        """Whether the slave reads the mapping back by complete access as it holds it (SOEM's
        ``config_map`` reads it so where the SII announces complete access)."""
        try:
            with self._lock:
                self.slave.sdo_read(0x1C00, 0, ca=True)
                for assign, pdo, layout in ((RX_ASSIGN, RX_MAP, rx), (TX_ASSIGN, TX_MAP, tx)):
                    a = self.slave.sdo_read(assign, 0, ca=True)
                    m = self.slave.sdo_read(pdo, 0, ca=True)
                    n = len(layout.objects)
                    if (len(a) < 4 or struct.unpack_from("<BxH", a) != (1, pdo) or len(m) < 2 + 4 * n
                            or list(struct.unpack_from(f"<Bx{n}I", m)) != [n, *layout.entries()]):  # fmt: skip
                        return False
        except Exception:  # pysoem's SdoError, PacketError ...: refused
            return False
        return True

    # -------------------------------------------------------------- states
    def read_state(self) -> tuple[int, int]:
        with self._lock, self.translated("reading the AL state"):
            self.master.read_state()
            return self.slave.state, self.slave.al_status

    def request(self, state: int) -> None:
        with self._lock, self.translated(f"requesting AL state 0x{state:02X}"):
            self.slave.state = state
            self.slave.write_state()

    def wait_state(self, target: int, cycling: bool = False) -> None:
        deadline = time.monotonic() + STATE_TIMEOUT_S
        while True:
            if cycling:
                self.cycle(self.outputs, count_errors=False)
            state, code = self.read_state()
            if state == target:
                return
            if state & AL_ACK:
                raise StateTransitionError(
                    f"{self.name} refused AL state 0x{target:02X}: in 0x{state & 0x0F:02X} with "
                    f"AL status code 0x{code:04X}"
                )
            if time.monotonic() > deadline:
                raise StateTransitionError(
                    f"{self.name} stayed in AL state 0x{state:02X}, expected 0x{target:02X} "
                    f"within {STATE_TIMEOUT_S} s"
                )
            time.sleep(0.001)

    def back_to_op(self) -> int | None:
        """OP again where the SM watchdog dropped the slave to SAFE-OP while the axis was not
        enabled (the host went silent longer than the watchdog: a stalled process, a slow
        import); ``None`` when the slave is in OP, else the AL status code recovered from.

        An axis that is not enabled produces no torque, so its watchdog trip stopped nothing:
        the error is acknowledged and OP requested, as a master does after such a trip.
        Any other state is an error naming it.
        """
        state, code = self.read_state()
        if state == OP:
            return None
        if state & 0x0F == SAFE_OP and code == AL_SM_WATCHDOG:
            self._op_through_safe_op(SAFE_OP | AL_ACK)
            return code
        raise StateTransitionError(
            f"{self.name} is in AL state 0x{state:02X} (AL status code 0x{code:04X}), not OP: "
            "close and open the drive again"
        )

    def _op_through_safe_op(self, request: int) -> None:
        """AL control ``request`` (SAFE-OP, or SAFE-OP with the error acknowledge), SAFE-OP
        awaited, valid outputs sent, then OP requested and awaited while cycling."""
        self.request(request)
        self.wait_state(SAFE_OP)
        self.cycle(self.outputs, count_errors=False)  # valid outputs before OP
        self.request(OP)
        self.wait_state(OP, cycling=True)

    def go_op(self, cycle_s: float) -> None:
        """PRE-OP -> SAFE-OP -> OP, with SYNC0 at ``cycle_s`` where the slave has DC."""
        if self.options.dc != "off":
            with self._lock, self.translated("distributed clocks (config_dc)"):
                self.has_dc = bool(self.master.config_dc())
            if self.options.dc == "on" and not self.has_dc:
                raise DriveConfigError(f"{self.name} has no distributed clocks (dc=on)")
            self.dc_synchronous = self.dc_synchronous and self.has_dc
            if self.has_dc:
                with self._lock, self.translated("SYNC0 (dc_sync)"):
                    self.slave.dc_sync(True, round(cycle_s * 1e9))
                    # SOEM chose the start time (0x0990): the SYNC0 grid of the slave's DC clock
                    self.sync0 = (struct.unpack("<Q", self.slave._fprd(0x0990, 8))[0],
                                  struct.unpack("<I", self.slave._fprd(0x09A0, 4))[0])  # fmt: skip
        self._op_through_safe_op(SAFE_OP)
        if self.dc_synchronous:  # SOEM starts SYNC0 a while ahead: no inputs until it runs
            deadline = time.monotonic() + STATE_TIMEOUT_S
            while self.cycle(self.outputs, count_errors=False)[1] < sum(self.sync0):
                if time.monotonic() > deadline:
                    raise StateTransitionError(f"{self.name}: SYNC0 did not start")
                time.sleep(0.001)

    def choose_dc_synchronous(self) -> str | None:
        """In PRE-OP: 0x1C32:01 = 2 (DC SYNC0) where 0x1C32:04 announces it (and ``dc`` is not off).

        :attr:`dc_synchronous` is then True once :meth:`go_op` found distributed clocks.
        Returns the refusal as a remark (the slave then runs as it is set), else ``None``.
        """
        self.dc_synchronous = False
        supported = self.sdo_optional(0x1C32, 4, "H") if self.options.dc != "off" else None
        if supported is None or not supported & 1 << SYNC_DC0:
            return None
        refused = self.sdo_write_optional(0x1C32, 1, "H", SYNC_DC0)
        self.dc_synchronous = refused is None
        return None if refused is None else f"DC-synchronous mode {refused}"

    def next_sync0(self, dc_ns: int) -> int:
        """The first SYNC0 event [ns of DC system time] after ``dc_ns``."""
        start, cycle = self.sync0
        return start + max(0, (dc_ns - start) // cycle + 1) * cycle

    def last_sync0(self, dc_ns: int) -> int:
        """The last SYNC0 event [ns of DC system time] at or before ``dc_ns``."""
        start, cycle = self.sync0
        return start + max(0, (dc_ns - start) // cycle) * cycle

    def back_to_pre_op(self) -> None:
        self.request(PRE_OP)
        self.wait_state(PRE_OP)

    def set_watchdog(self, timeout_s: float) -> None:
        with self._lock, self.translated("SM watchdog"):
            limit_ms = self.slave.get_max_watchdog_time()
            ms = min(timeout_s * 1e3, limit_ms)
            self.slave.set_watchdog("processdata", round(ms, 1))

    # --------------------------------------------------------------- cycle
    def cycle(self, outputs: bytes, count_errors: bool = True) -> tuple[bytes, int]:
        """One valid frame: ``(inputs, DC system time [ns])``; raises when the link is lost.

        A frame that does not come back within ``frame_timeout`` or with a wrong
        working counter is counted and sent again (its inputs are not the slave's),
        up to ``max_wkc_errors`` times in a row.
        """
        with self._lock:
            return self._cycle_locked(outputs, count_errors)

    def _cycle_locked(self, outputs: bytes | None, count_errors: bool = True) -> tuple[bytes, int]:
        """:meth:`cycle` with the lock held; ``outputs`` None: the last sent again (read under the
        lock, so a frame sent meanwhile is never undone by an older one)."""
        outputs = self.outputs if outputs is None else outputs
        self.outputs = outputs
        self.slave.output = outputs
        timeout_us = round(self.options.frame_timeout_s * 1e6)
        for _ in range(self.options.max_wkc_errors):
            self.master.send_processdata()
            # the GIL released while SOEM waits: the host's other threads (the log writer) run
            wkc = self.master.receive_processdata(timeout_us, release_gil=True)
            self._last_cycle = time.monotonic()
            if wkc == self.master.expected_wkc:
                return bytes(self.slave.input), int(self.master.dc_time)
            if not count_errors:
                return bytes(self.slave.input), int(self.master.dc_time)
            self.wkc_errors += 1
        raise DriveConnectionError(
            f"{self.name}: {self.options.max_wkc_errors} frames in a row lost or with a wrong working counter "
            f"(last {wkc}, expected {self.master.expected_wkc}): link lost; "
            "the slave's SM watchdog stops the axis"
        )

    def start_keepalive(self) -> None:
        self._stop.clear()
        self._keepalive = threading.Thread(target=self._keepalive_run, name="ethercat-keepalive",
                                           daemon=True)  # fmt: skip
        self._keepalive.start()

    def _keepalive_run(self) -> None:
        while not self._stop.wait(KEEPALIVE_S / 2):
            if not self.keep_alive or time.monotonic() - self._last_cycle < KEEPALIVE_S:
                continue
            try:
                # the outputs read under the lock, and the need checked again there: outputs taken
                # before the host's own frame (a controlword 0 before an enable) and sent after it
                # would undo it (0x0260: SWITCH ON DISABLED right after OPERATION ENABLED)
                with self._lock:
                    if self.keep_alive and time.monotonic() - self._last_cycle >= KEEPALIVE_S:
                        self._cycle_locked(None)
            except (DriveError, OSError) as err:
                self.keepalive_error = err
                return

    def stop_keepalive(self) -> None:
        self._stop.set()
        if self._keepalive is not None:
            self._keepalive.join(1.0)
            self._keepalive = None

    def close(self, read_only: bool = False) -> None:
        """Disarm the SM watchdog, the slave to INIT, the socket closed; safe twice.

        ``read_only``: nothing written (no watchdog was armed): the slave stays in PRE-OP.
        """
        self.stop_keepalive()
        if self.master is None:
            return
        if read_only:
            self.close_socket()
            return
        try:
            with self._lock:
                self.slave.set_watchdog("processdata", 0)
            self.request(INIT)
        except Exception:  # closing what may be a broken link: the socket goes anyway
            pass
        finally:
            self.close_socket()


def _mapping_text(assigned: list[int], entries: list[int]) -> str:
    """``0x1600 [0x60400010, 0x60710010]``: the PDOs assigned and the entries of the PDO."""
    return (f"{', '.join(f'0x{p:04X}' for p in assigned) or 'nothing assigned'} "
            f"[{', '.join(f'0x{e:08X}' for e in entries)}]")  # fmt: skip

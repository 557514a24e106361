"""The EtherCAT master of the ``ethercat://`` drive: pysoem (SOEM) session and cycle.

:class:`EthercatMaster` owns everything pysoem does for the drive, and turns
pysoem's exceptions into servobench's typed errors at this boundary:

* bring-up in PRE-OP: scan (``config_init``), the slave at position
  ``slave``, its identity (SII and 0x1018), the CiA 402 check (0x1000 device
  profile 402, 0x6502 modes), SDO access with typed errors;
* the PDO mapping (:mod:`.layout`): 0x1C12/0x1C13 and 0x1600/0x1A00 written
  by complete access, and entry by entry when the slave refuses it (abort),
  then ``config_map`` and a check of the sizes the slave took;
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

import struct
import threading
import time
from collections.abc import Callable
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

    # ----------------------------------------------------------------- SDO
    def sdo_read(self, index: int, sub: int, fmt: str) -> Any:
        data = self._sdo(lambda: self.slave.sdo_read(index, sub), index, sub)
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
        self._sdo(lambda: self.slave.sdo_write(index, sub, data, ca=ca), index, sub)

    def _sdo(self, call: Callable[[], Any], index: int, sub: int) -> Any:
        p = self.pysoem
        with self._lock:
            try:
                return call()
            except p.SdoError as err:
                error = DriveConfigError(
                    f"{self.name}: SDO 0x{index:04X}:{sub} aborted 0x{err.abort_code:08X} ({err.desc})"
                )
                error.abort_code = err.abort_code
                raise error from None
            except (p.PacketError, p.MailboxError, p.WkcError) as err:
                raise DriveTimeoutError(
                    f"{self.name}: SDO 0x{index:04X}:{sub} failed: {err!r}"
                ) from None

    # ------------------------------------------------------------- mapping
    def map_pdos(self, rx_present: list[int], tx_present: list[int]) -> None:
        """Write the mapping (complete access first), then let SOEM map it."""
        rx = PdoLayout.choose(RX_OBJECTS, rx_present)
        tx = PdoLayout.choose(TX_OBJECTS, tx_present)
        for layout, required in ((rx, REQUIRED_RX), (tx, REQUIRED_TX)):
            missing = [f"0x{i:04X}" for i in required if not layout.has(i)]
            if missing:
                raise DriveConfigError(f"{self.name} lacks {', '.join(missing)}: no CiA 402 drive")
        self._write_pdo(RX_ASSIGN, RX_MAP, rx.entries())
        try:
            self._write_pdo(TX_ASSIGN, TX_MAP, tx.entries())
        except DriveConfigError:
            if not any(tx.has(i) for i in TIMESTAMPS):
                raise
            tx = PdoLayout(tuple(o for o in tx.objects if o[0] not in TIMESTAMPS))  # not mappable
            self._write_pdo(TX_ASSIGN, TX_MAP, tx.entries())
        self.rx, self.tx = rx, tx
        self.master.config_map()
        got = (len(self.slave.output), len(self.slave.input))
        if got != (rx.size, tx.size):
            raise DriveConfigError(
                f"{self.name} mapped {got[0]}/{got[1]} output/input bytes, not {rx.size}/{tx.size}"
            )
        self.outputs = bytes(rx.size)

    def _write_pdo(self, assign: int, pdo: int, entries: list[int]) -> None:
        if self.complete_access:
            try:
                self.sdo_write(assign, 0, struct.pack("<BxH", 1, pdo), ca=True)
                self.sdo_write(pdo, 0, struct.pack(f"<Bx{len(entries)}I", len(entries), *entries),
                               ca=True)  # fmt: skip
                return
            except DriveConfigError:
                self.complete_access = False  # refused: entry by entry, as CiA 301 does it
        self.sdo_write(assign, 0, b"\x00")
        self.sdo_write(pdo, 0, b"\x00")
        for sub, entry in enumerate(entries, start=1):
            self.sdo_write(pdo, sub, struct.pack("<I", entry))
        self.sdo_write(pdo, 0, bytes([len(entries)]))
        self.sdo_write(assign, 1, struct.pack("<H", pdo))
        self.sdo_write(assign, 0, b"\x01")

    # -------------------------------------------------------------- states
    def read_state(self) -> tuple[int, int]:
        with self._lock:
            self.master.read_state()
            return self.slave.state, self.slave.al_status

    def request(self, state: int) -> None:
        with self._lock:
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

    def go_op(self, cycle_s: float) -> None:
        """PRE-OP -> SAFE-OP -> OP, with SYNC0 at ``cycle_s`` where the slave has DC."""
        if self.options.dc != "off":
            with self._lock:
                self.has_dc = bool(self.master.config_dc())
            if self.options.dc == "on" and not self.has_dc:
                raise DriveConfigError(f"{self.name} has no distributed clocks (dc=on)")
            self.dc_synchronous = self.dc_synchronous and self.has_dc
            if self.has_dc:
                with self._lock:
                    self.slave.dc_sync(True, round(cycle_s * 1e9))
                    # SOEM chose the start time (0x0990): the SYNC0 grid of the slave's DC clock
                    self.sync0 = (struct.unpack("<Q", self.slave._fprd(0x0990, 8))[0],
                                  struct.unpack("<I", self.slave._fprd(0x09A0, 4))[0])  # fmt: skip
        self.request(SAFE_OP)
        self.wait_state(SAFE_OP)
        self.cycle(self.outputs, count_errors=False)  # valid outputs before OP
        self.request(OP)
        self.wait_state(OP, cycling=True)
        if self.dc_synchronous:  # SOEM starts SYNC0 a while ahead: no inputs until it runs
            deadline = time.monotonic() + STATE_TIMEOUT_S
            while self.cycle(self.outputs, count_errors=False)[1] < sum(self.sync0):
                if time.monotonic() > deadline:
                    raise StateTransitionError(f"{self.name}: SYNC0 did not start")
                time.sleep(0.001)

    def choose_dc_synchronous(self) -> None:
        """In PRE-OP: 0x1C32:01 = 2 (DC SYNC0) where 0x1C32:04 announces it (and ``dc`` is not off).

        :attr:`dc_synchronous` is then True once :meth:`go_op` found distributed clocks.
        """
        self.dc_synchronous = False
        supported = self.sdo_optional(0x1C32, 4, "H") if self.options.dc != "off" else None
        if supported is None or not supported & 1 << SYNC_DC0:
            return
        try:
            self.sdo_write(0x1C32, 1, struct.pack("<H", SYNC_DC0))
        except DriveConfigError:
            return
        self.dc_synchronous = True

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
        with self._lock:
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
                self.cycle(self.outputs)
            except (DriveError, OSError) as err:
                self.keepalive_error = err
                return

    def stop_keepalive(self) -> None:
        self._stop.set()
        if self._keepalive is not None:
            self._keepalive.join(1.0)
            self._keepalive = None

    def close(self) -> None:
        """Disarm the SM watchdog, the slave to INIT, the socket closed; safe twice."""
        self.stop_keepalive()
        if self.master is None:
            return
        try:
            with self._lock:
                self.slave.set_watchdog("processdata", 0)
            self.request(INIT)
        except Exception:  # closing what may be a broken link: the socket goes anyway
            pass
        finally:
            self.close_socket()

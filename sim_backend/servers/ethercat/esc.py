"""The EtherCAT slave controller (ESC): register space, datagrams, SyncManagers, FMMUs.

:class:`Esc` executes datagrams on its register space (:mod:`.registers`) as
an ESC does and answers with the working counter an ESC gives:

========================  ===========================  ==================================
command                   addressed when               working counter (this slave)
========================  ===========================  ==================================
APRD/APWR/APRW            ADP = 0 (ADP incremented)    read +1, write +1; RW: +1 / +2
FPRD/FPWR/FPRW            ADP = station address        same; RW returns the data before
BRD/BWR/BRW               always (ADP incremented)     same; BRD/BRW OR their data in
LRD/LWR/LRW               an active FMMU overlaps      read +1, write +1; LRW: +1 / +2
ARMW (ADP = 0), FRMW      reads there, writes elsewhere +1
========================  ===========================  ==================================

A physical access that reaches a SyncManager's buffer obeys it: a mailbox
buffer written full by the master is handed to the application
(:meth:`Application.mailbox_written`) and refuses further writes until the
application took it (no working counter); the application's reply buffer
refuses reads while empty and empties when its last byte is read; a write
that completes the process data output buffer (SM2) hands it to the
application and retriggers the SM watchdog (control bit 6). Register side
effects: AL control, the EEPROM command, the SyncManager activation and
repeat request, the DC receive-time latch, system time and SYNC0 activation.

Simplifications: one port (the end of the line); the application answers
within the datagram (an LRW writes the outputs, the application runs, and
the inputs it produced are read back in the same pass, where a real PDI
would answer in the next frame); the three process data buffers are one;
bitwise FMMU mappings are treated as bytewise.
"""

from __future__ import annotations

import contextlib
import struct
import time
from collections.abc import Callable, Iterator

from servobench.sim_backend.servers.ethercat import al
from servobench.sim_backend.servers.ethercat import registers as R
from servobench.sim_backend.servers.ethercat.eeprom import execute_eeprom_command
from servobench.sim_backend.servers.ethercat.frame import Command, Datagram

_READ_WKC, _WRITE_WKC = 1, 1
_RW_WRITE_WKC = 2


class Application:
    """What runs behind the ESC's PDI; the defaults do nothing."""

    def al_transition(self, current: al.AlState, target: al.AlState) -> int:
        """The master asks for ``target``: the AL status code (0: done, ``al.PENDING``: later)."""
        return al.NO_ERROR

    def mailbox_written(self, data: bytes) -> None:
        """The master filled the receive mailbox (SM0) with ``data``."""

    def outputs_written(self, data: bytes) -> None:
        """The master completed the output buffer (SM2) with ``data``."""

    def watchdog_expired(self) -> None:
        """The SM watchdog expired (no outputs within its time)."""


class Esc:
    """An ESC with an SII image, serving ``app``.

    Parameters
    ----------
    sii : bytes
        The EEPROM content (:func:`.sii.build_image`).
    app : Application
        The application behind the PDI.
    clock_ns : callable
        The local clock of the DC unit [ns].
    """

    def __init__(
        self, sii: bytes, app: Application, clock_ns: Callable[[], int] = time.monotonic_ns
    ) -> None:
        self.sii = bytearray(sii)
        self.app = app
        self._clock_ns = clock_ns
        self._t0_ns = clock_ns()
        self._frame_ns: int | None = None  # the arrival instant of the frame being processed
        self.mem = R.reset_image()
        self._mask = R.write_mask()
        self._mailbox_full = [False] * R.SM_COUNT
        self._last_reply = b""
        self._reply_queue: list[bytes] = []
        self._last_output_ns: int | None = None
        self._wd_expired = False
        pdi, config = self.sii[0], self.sii[1]
        self.mem[R.PDI_CONTROL], self.mem[R.ESC_CONFIG] = pdi, config
        self.mem[R.STATION_ALIAS : R.STATION_ALIAS + 2] = self.sii[8:10]

    # ------------------------------------------------------------- state
    @property
    def al_state(self) -> al.AlState:
        return al.AlState(self.mem[R.AL_STATUS] & al.STATE_MASK)

    @property
    def al_error(self) -> bool:
        return bool(self.mem[R.AL_STATUS] & al.ERROR_FLAG)

    def word(self, address: int) -> int:
        return int.from_bytes(self.mem[address : address + 2], "little")

    def set_al(self, state: al.AlState, code: int = al.NO_ERROR) -> None:
        """Enter ``state``; a non-zero ``code`` sets the error flag and the status code."""
        self.mem[R.AL_STATUS : R.AL_STATUS + 2] = al.encode_status(state, code != 0).to_bytes(
            2, "little"
        )
        if code:
            self.mem[R.AL_STATUS_CODE : R.AL_STATUS_CODE + 2] = code.to_bytes(2, "little")

    def local_time_ns(self) -> int:
        """The DC unit's local time [ns]; while a frame passes, the instant it arrived."""
        now = self._clock_ns() if self._frame_ns is None else self._frame_ns
        return now - self._t0_ns

    @contextlib.contextmanager
    def frame_at(self, arrival_ns: int) -> Iterator[None]:
        """Process one frame at its arrival instant ``arrival_ns`` (of the ESC's clock).

        A frame passes an ESC in microseconds: every datagram in it (the
        process data, the DC system time an FRMW reads) sees the one instant.
        """
        self._frame_ns = arrival_ns
        try:
            yield
        finally:
            self._frame_ns = None

    def system_time_ns(self) -> int:
        """DC system time: local time plus the offset the master wrote (0x0920) [ns]."""
        return self.system_time_of(self.local_time_ns())

    def system_time_at(self, clock_ns: int) -> int:
        """The DC system time [ns] when the ESC clock (``clock_ns``) reads ``clock_ns``."""
        return self.system_time_of(clock_ns - self._t0_ns)

    def clock_of_system(self, system_ns: int) -> int:
        """The ESC clock's reading [ns] (``clock_ns``) when the DC system time is ``system_ns``."""
        (offset,) = struct.unpack_from("<q", self.mem, R.DC_SYSTEM_TIME_OFFSET)
        return (system_ns - offset) % 2**64 + self._t0_ns

    def system_time_of(self, local_ns: int) -> int:
        """The DC system time [ns] of the local time ``local_ns`` (plus the offset 0x0920)."""
        (offset,) = struct.unpack_from("<q", self.mem, R.DC_SYSTEM_TIME_OFFSET)
        return (local_ns + offset) & 0xFFFFFFFFFFFFFFFF

    def sync0(self) -> tuple[int, int] | None:
        """``(start time, cycle)`` [ns of system time] while SYNC0 is active, else ``None``."""
        if self.mem[R.DC_ACTIVATION] & 0x03 != 0x03:
            return None
        (start,) = struct.unpack_from("<Q", self.mem, R.DC_START_TIME)
        (cycle,) = struct.unpack_from("<I", self.mem, R.DC_SYNC0_CYCLE)
        return start, cycle

    # ------------------------------------------------------ SyncManagers
    def sm(self, n: int) -> tuple[int, int, int, bool]:
        """SyncManager ``n``: ``(start, length, control, enabled)``."""
        start, length, control, _status, activate = struct.unpack_from(
            "<HHBBB", self.mem, R.sm_register(n)
        )
        return start, length, control, bool(activate & R.SM_ACTIVATE_ENABLE) and length > 0

    def _sm_at(self, address: int, n: int) -> int | None:
        for k in range(R.SM_COUNT):
            start, length, _control, enabled = self.sm(k)
            if enabled and address < start + length and start < address + n:
                return k
        return None

    def _set_mailbox_full(self, n: int, full: bool) -> None:
        self._mailbox_full[n] = full
        status = R.sm_register(n, R.SM_STATUS)
        if full:
            self.mem[status] |= R.SM_STATUS_MAILBOX_FULL
        else:
            self.mem[status] &= ~R.SM_STATUS_MAILBOX_FULL & 0xFF

    def _reply_sm(self) -> int | None:
        for k in range(R.SM_COUNT):
            _start, _length, control, enabled = self.sm(k)
            if enabled and control & 0x0F == R.SM_MODE_MAILBOX:  # mailbox, ECAT reads
                return k
        return None

    def post_mailbox(self, data: bytes) -> None:
        """The application's reply for the master (queued while the send mailbox is full)."""
        self._reply_queue.append(bytes(data))
        self._deliver_reply()

    def _deliver_reply(self) -> None:
        n = self._reply_sm()
        if n is None or self._mailbox_full[n] or not self._reply_queue:
            return
        start, length, _control, _enabled = self.sm(n)
        data = self._reply_queue.pop(0)[:length]
        self.mem[start : start + length] = data + bytes(length - len(data))
        self._last_reply = data
        self._set_mailbox_full(n, True)

    def reset_mailboxes(self) -> None:
        """Forget buffered mailbox content (the slave went to INIT)."""
        self._reply_queue.clear()
        for k in range(R.SM_COUNT):
            self._set_mailbox_full(k, False)

    def set_inputs(self, n: int, data: bytes) -> None:
        """The application writes ``data`` into the input buffer of SyncManager ``n``."""
        start, length, _control, _enabled = self.sm(n)
        self.mem[start : start + min(length, len(data))] = data[:length]

    # -------------------------------------------------------- watchdog
    def watchdog_s(self) -> float | None:
        """The process data watchdog time [s], ``None`` when off (time 0 or SM2 bit 6 clear)."""
        _start, _length, control, enabled = self.sm(2)
        ticks = self.word(R.WD_TIME_PD)
        if not enabled or not control & R.SM_WATCHDOG_ENABLE or ticks == 0:
            return None
        return ticks * (self.word(R.WD_DIVIDER) + 2) * 40e-9

    def poll(self) -> None:
        """Check the SM watchdog (call at least every millisecond or so)."""
        timeout = self.watchdog_s()
        if timeout is None or self._last_output_ns is None or self._wd_expired:
            return
        if self._clock_ns() - self._last_output_ns > timeout * 1e9:
            self._wd_expired = True
            self.mem[R.WD_STATUS_PD] &= 0xFE
            self.mem[R.WD_COUNTER_PD] = min(self.mem[R.WD_COUNTER_PD] + 1, 0xFF)
            self.app.watchdog_expired()

    def _outputs(self, n: int) -> None:
        start, length, _control, _enabled = self.sm(n)
        self._last_output_ns = self._clock_ns()
        if self._wd_expired:
            self._wd_expired = False
            self.mem[R.WD_STATUS_PD] |= 0x01
        self.app.outputs_written(bytes(self.mem[start : start + length]))

    # ------------------------------------------------- physical access
    def read(self, address: int, n: int) -> bytes | None:
        """``n`` bytes at ``address`` as the master reads them; ``None``: access refused."""
        if address + n > R.RAM_END:
            return None
        self._refresh(address, n)
        k = self._sm_at(address, n)
        if k is not None:
            start, length, control, _enabled = self.sm(k)
            if control & 0x03 == R.SM_MODE_MAILBOX and not control & R.SM_DIR_WRITE:
                if not self._mailbox_full[k]:
                    return None
                data = bytes(self.mem[address : address + n])
                if address + n >= start + length:
                    self._set_mailbox_full(k, False)
                    self._deliver_reply()
                return data
        return bytes(self.mem[address : address + n])

    def write(self, address: int, data: bytes) -> bool:
        """Write ``data`` at ``address`` as the master does; False: access refused."""
        n = len(data)
        if address + n > R.RAM_END:
            return False
        k = self._sm_at(address, n)
        if k is not None and address >= R.RAM_START:
            start, length, control, _enabled = self.sm(k)
            if not control & R.SM_DIR_WRITE:
                return False  # the application's buffer
            if control & 0x03 == R.SM_MODE_MAILBOX and self._mailbox_full[k]:
                return False
            self.mem[address : address + n] = data
            if address + n >= start + length:
                if control & 0x03 == R.SM_MODE_MAILBOX:
                    self._set_mailbox_full(k, True)
                    payload = bytes(self.mem[start : start + length])
                    self._set_mailbox_full(k, False)  # the application takes it at once
                    self.app.mailbox_written(payload)
                else:
                    self._outputs(k)
            return True
        if address >= R.RAM_START:
            self.mem[address : address + n] = data
            return True
        before = bytes(self.mem[address : address + n])
        for i, byte in enumerate(data):
            if self._mask[address + i]:
                self.mem[address + i] = byte
        self._side_effects(address, n, before)
        return True

    def _refresh(self, address: int, n: int) -> None:
        """Registers whose value is computed when read."""
        if address < R.DC_SYSTEM_TIME + 8 and address + n > R.DC_SYSTEM_TIME:
            struct.pack_into("<Q", self.mem, R.DC_SYSTEM_TIME, self.system_time_ns())

    def _touches(self, address: int, n: int, register: int, size: int = 1) -> bool:
        return address < register + size and register < address + n

    def _side_effects(self, address: int, n: int, before: bytes) -> None:
        if self._touches(address, n, R.AL_CONTROL):
            self._al_control()
        if self._touches(address, n, R.EEPROM_CONTROL, 2):
            self._eeprom_command()
        if self._touches(address, n, R.DC_RECEIVE_TIME_PORT0):
            local = self.local_time_ns()
            for port in range(4):
                struct.pack_into(
                    "<I", self.mem, R.DC_RECEIVE_TIME_PORT0 + 4 * port, local & 0xFFFFFFFF
                )
            struct.pack_into("<Q", self.mem, R.DC_RECEIVE_TIME_PU, local)
        if self._touches(address, n, R.DC_SYSTEM_TIME, 8):
            # the reference clock's time (ARMW/FRMW drift compensation): keep the difference
            (ref,) = struct.unpack_from("<Q", self.mem, R.DC_SYSTEM_TIME)
            diff = (ref - self.system_time_ns() + 2**63) % 2**64 - 2**63
            struct.pack_into(
                "<i", self.mem, R.DC_SYSTEM_TIME_DIFF, max(-(2**31), min(diff, 2**31 - 1))
            )
        if self._touches(address, n, R.DC_ACTIVATION):
            self.mem[R.DC_SYNC0_STATUS] = 1 if self.sync0() else 0
        for k in range(R.SM_COUNT):
            base = R.sm_register(k)
            if self._touches(address, n, base, R.SM_BYTES):
                self._sm_written(k, before, address)

    def _sm_written(self, k: int, before: bytes, address: int) -> None:
        activate = R.sm_register(k, R.SM_ACTIVATE)
        old = before[activate - address] if address <= activate < address + len(before) else None
        new = self.mem[activate]
        if old is None:
            return
        if (old ^ new) & R.SM_ACTIVATE_ENABLE:
            self._set_mailbox_full(k, False)  # (de)activating resets the buffer
            self._deliver_reply()
        if (old ^ new) & R.SM_ACTIVATE_REPEAT and self._last_reply:
            # repeat request: the last reply again, then acknowledge in the PDI control
            start, length, _control, _enabled = self.sm(k)
            self.mem[start : start + length] = self._last_reply + bytes(
                length - len(self._last_reply)
            )
            self._set_mailbox_full(k, True)
            pdi = R.sm_register(k, R.SM_PDI_CONTROL)
            self.mem[pdi] = (self.mem[pdi] & ~R.SM_ACTIVATE_REPEAT & 0xFF) | (
                new & R.SM_ACTIVATE_REPEAT
            )

    # ------------------------------------------------------ AL control
    def _al_control(self) -> None:
        request = al.decode_control(self.word(R.AL_CONTROL))
        current = self.al_state
        if self.al_error and al.ignored_while_in_error(current, request):
            return
        error = self.al_error and not request.acknowledge
        if request.acknowledge:
            self.mem[R.AL_STATUS_CODE : R.AL_STATUS_CODE + 2] = b"\x00\x00"
        code = al.check_request(current, request)
        if code == al.NO_ERROR and request.target is al.AlState.BOOT:
            code = al.BOOT_NOT_SUPPORTED
        if code:
            self.set_al(current, code)
            return
        target = request.target
        if target is not current:
            code = self.app.al_transition(current, target)
        if code == al.PENDING:
            return
        if code:
            self.set_al(current, code)
        else:
            self.set_al(target)
            if error:
                self.mem[R.AL_STATUS] |= al.ERROR_FLAG

    # ----------------------------------------------------------- EEPROM
    def _eeprom_command(self) -> None:
        execute_eeprom_command(self.mem, self.sii)

    # -------------------------------------------------------- datagrams
    def execute(self, dg: Datagram) -> Datagram:
        """The datagram as this slave passes it on."""
        cmd = dg.command
        if cmd is Command.NOP:
            return dg
        if cmd.logical:
            return self._logical(dg)
        station = self.word(R.STATION_ADDRESS)
        if cmd in (Command.APRD, Command.APWR, Command.APRW, Command.ARMW):
            addressed, adp = dg.adp == 0, (dg.adp + 1) & 0xFFFF
        elif cmd in (Command.BRD, Command.BWR, Command.BRW):
            addressed, adp = True, (dg.adp + 1) & 0xFFFF
        else:
            addressed, adp = dg.adp == station, dg.adp
        data, wkc = dg.data, dg.wkc
        if cmd in (Command.ARMW, Command.FRMW):
            if addressed:
                got = self.read(dg.ado, len(dg.data))
                if got is not None:
                    data, wkc = got, wkc + _READ_WKC
            elif self.write(dg.ado, dg.data):
                wkc += _WRITE_WKC
            return dg.answered(data, wkc, adp)
        if not addressed:
            return dg.answered(data, wkc, adp)
        if cmd.reads:  # read before write, as the frame passes (xPRW return the old data)
            got = self.read(dg.ado, len(dg.data))
            if got is not None:
                if cmd in (Command.BRD, Command.BRW):
                    got = bytes(a | b for a, b in zip(dg.data, got, strict=True))
                data, wkc = got, wkc + _READ_WKC
        if cmd.writes and self.write(dg.ado, dg.data):
            wkc += _RW_WRITE_WKC if cmd.reads else _WRITE_WKC
        return dg.answered(data, wkc, adp)

    def fmmus(self) -> list[tuple[int, int, int, int]]:
        """Active FMMUs: ``(logical start, length, physical start, type)``."""
        out = []
        for k in range(R.FMMU_COUNT):
            base = R.FMMU0 + k * R.FMMU_BYTES
            log, length, _sb, _eb, phys, _pb, kind, active = struct.unpack_from(
                "<IHBBHBBB", self.mem, base
            )
            if active & 0x01 and length:
                out.append((log, length, phys, kind))
        return out

    def _logical(self, dg: Datagram) -> Datagram:
        cmd, address, n = dg.command, dg.logical_address, len(dg.data)
        data = bytearray(dg.data)
        read_ok = write_ok = False
        mapped = [
            (log, length, phys, kind)
            for log, length, phys, kind in self.fmmus()
            if address < log + length and log < address + n
        ]
        if cmd in (Command.LWR, Command.LRW):
            for log, length, phys, kind in mapped:
                if kind & 0x02:
                    lo, hi = max(address, log), min(address + n, log + length)
                    ok = self.write(phys + lo - log, bytes(dg.data[lo - address : hi - address]))
                    write_ok = write_ok or ok
        if cmd in (Command.LRD, Command.LRW):
            for log, length, phys, kind in mapped:
                if kind & 0x01:
                    lo, hi = max(address, log), min(address + n, log + length)
                    got = self.read(phys + lo - log, hi - lo)
                    if got is not None:
                        data[lo - address : hi - address] = got
                        read_ok = True
        wkc = dg.wkc + (_READ_WKC if read_ok else 0)
        if write_ok:
            wkc += _RW_WRITE_WKC if cmd is Command.LRW else _WRITE_WKC
        return dg.answered(bytes(data), wkc)

"""``serial://`` -- drives that speak a line-based ASCII protocol over a serial port.

``serial:///dev/ttyACM0?baud=115200&dialect=odrive`` opens the port with
pyserial and talks the dialect (:mod:`servobench.drivers.dialect`) named by
``dialect`` -- a shipped name or a path to a TOML file. The default,
``odrive``, is the ODrive ASCII protocol of firmware 0.5.x
(https://docs.odriverobotics.com/v/0.5.5/ascii-protocol.html); its units are
torque ``u`` [Nm], position ``x`` [turn] and velocity ``v`` [turn/s].

Query keys
----------
``baud``      bit rate [bit/s], default 115200 (ignored by USB CDC ports)
``dialect``   dialect name or TOML file, default ``odrive``
``axis``      axis (motor) number, default from the dialect
``checksum``  1 to append ``*<xor>`` checksums (and demand them on replies)
``timeout``   reply deadline [s], default :data:`REPLY_TIMEOUT_S`
``poll``      fault poll period while streaming [s], default :data:`FAULT_POLL_S`; 0 = never

Cycle semantics
---------------
:meth:`Drive.exchange` writes the torque command and the feedback query in
one write and reads the feedback reply: on the lock-step simulator the
command latches and the feedback query clocks one cycle (sample at ``t_k``,
then ``u_k`` acts), which is the :class:`~servobench.drivers.base.Drive` contract. A real
ODrive runs its own loop; there the reply is the latest estimate. Every
``poll`` seconds the error register is read in the same write, and a fault
raises :class:`~servobench.errors.DriveFaultError` with the drive's code.
Feedback ``t_s`` is the host's ``time.monotonic()`` at reception (the
protocol carries no drive clock).

Before each request the driver looks for bytes nobody asked for: an exact
repeat of the last reply line (a duplicated reply) is dropped and counted in
:attr:`SerialAsciiDrive.duplicates`; anything else means the last reply may
not have answered the last request, so :class:`MalformedReplyError` is
raised and the line is resynchronised before the next request.

Set-up on the drive: :meth:`open` resynchronises the line and reads the error
register; the watchdog is armed as ``w axis0.config.watchdog_timeout <s>``,
``u 0``, ``w axis0.config.enable_watchdog 1`` and read back; :meth:`enable`
refuses a drive in fault, sends ``c 0 0`` (torque control, zero torque) and
``w axis0.requested_state 8`` and waits for ``r axis0.current_state`` to read
8 (:class:`~servobench.errors.StateTransitionError` if it does not, or
:class:`~servobench.errors.DriveFaultError` with ``axis0.error`` if that is set);
:meth:`reset_fault` is ``sc``; :meth:`set_cycle` uses the dialect's servobench
extension and, if the drive rejects it (a stock ODrive), records the drive as
free-running (:attr:`SerialAsciiDrive.lockstep` is False).

Not confirmed against hardware (no ODrive here): see the caveats at the top
of ``drivers/data/dialects/odrive.toml`` (firmware 0.6 property names, the
9-character limit of ``r`` replies, the ``sc`` command's first release, the
"lu" error-read bug). Without ``checksum=1`` a reply that loses digits, not its line end,
still parses (e.g. ``0.12345`` for ``0.123456``); only checksums catch that.
POSIX only (waits with ``select`` on the port's file descriptor).
"""

from __future__ import annotations

import math
import select
import time
from collections import deque

import serial

from servobench.drivers.ascii_line import MalformedReplyError, decode_reply, encode_line
from servobench.drivers.base import Drive, DriveInfo, Feedback
from servobench.drivers.dialect import (
    COMMAND_SPECS,
    CommandRejectedError,
    Dialect,
    ParsedLine,
    load_dialect,
)
from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveFaultError,
    DriveTimeoutError,
    StateTransitionError,
)

DEFAULT_BAUD = 115200
#: Deadline for one reply line [s].
REPLY_TIMEOUT_S = 0.1
#: Deadline for a blocked write [s].
WRITE_TIMEOUT_S = 0.5
#: Deadline for the closed-loop / idle state to be reached [s].
STATE_TIMEOUT_S = 2.0
#: Pause between state reads while waiting for a transition [s].
STATE_POLL_S = 0.005
#: Silence that ends the resynchronisation drain on open [s].
RESYNC_QUIET_S = 0.05
#: Longest resynchronisation before the drive is deemed to talk nonstop [s].
RESYNC_MAX_S = 1.0
#: Default period of the error-register read while streaming [s].
FAULT_POLL_S = 0.1
#: Longest reply line accepted [bytes] (the ODrive's transmit buffer is 64).
MAX_LINE_BYTES = 256
#: Relative tolerance of read-backs (the firmware answers reads with <= 9 characters).
READBACK_RTOL = 1e-3


class SerialAsciiDrive(Drive):
    """A drive on a serial port speaking a line-based ASCII :class:`~servobench.drivers.dialect.Dialect`."""

    query_keys = frozenset({"baud", "dialect", "axis", "checksum", "timeout", "poll"})

    def __init__(self, url) -> None:
        super().__init__(url)
        self.port = self.url.path or self.url.host
        if not self.port:
            raise DriveConfigError(
                "serial:// needs a port, e.g. serial:///dev/ttyACM0?baud=115200&dialect=odrive"
            )
        self.baud = self.url.get_int("baud", DEFAULT_BAUD)
        if not self.baud > 0:
            raise DriveConfigError(f"baud must be > 0, got {self.baud}")
        self.dialect: Dialect = load_dialect(self.url.get_str("dialect", "odrive"))
        self.axis = self.url.get_int("axis", self.dialect.axis)
        self.use_checksum = self.url.get_bool("checksum", self.dialect.use_checksum)
        if self.use_checksum and self.dialect.checksum == "none":
            raise DriveConfigError(f"dialect {self.dialect.name!r} has no checksum")
        self.reply_timeout_s = self.url.get_float("timeout", REPLY_TIMEOUT_S)
        self.poll_s = self.url.get_float("poll", FAULT_POLL_S)
        if not self.reply_timeout_s > 0 or self.poll_s < 0:
            raise DriveConfigError("timeout must be > 0 s and poll >= 0 s")
        self.units = dict(self.dialect.units)
        #: False once a drive rejected the cycle extension (it runs its own loop).
        self.lockstep: bool | None = None
        self._serial: serial.Serial | None = None
        self._rx = bytearray()
        self._sent: deque[str] = deque(maxlen=8)  # requests not yet followed by a reply
        self._next_poll = 0.0
        self._out_of_step = False
        self._last_line = b""  # the last reply line, terminator included
        #: Repeated reply lines dropped (see the module docstring).
        self.duplicates = 0
        #: Bytes written to / read from the port since it was opened (for rate figures).
        self.bytes_sent = 0
        self.bytes_received = 0

    # ------------------------------------------------------------- line I/O
    def _send(self, *bodies: str) -> None:
        """Write request lines in one write (after a resync if the last exchange broke off)."""
        ser = self._port()
        if self._out_of_step:
            self._resync(end_drive_line=False)
        else:
            self._check_unsolicited(ser)
        raw = b"".join(encode_line(b, self.dialect.terminator, self.use_checksum) for b in bodies)
        self._sent.extend(bodies)
        try:
            ser.write(raw)
            self.bytes_sent += len(raw)
        except serial.SerialTimeoutException as err:
            raise DriveTimeoutError(f"{self.port}: write blocked for {WRITE_TIMEOUT_S} s") from err
        except (serial.SerialException, OSError) as err:
            raise DriveConnectionError(f"{self.port}: write failed: {err}") from err

    def _check_unsolicited(self, ser: serial.Serial) -> None:
        """Drop a repeated last reply; raise on any other bytes that came unasked."""
        try:
            waiting = ser.in_waiting
            if waiting:
                self._rx += ser.read(waiting)
                self.bytes_received += waiting
        except (serial.SerialException, OSError) as err:
            raise DriveConnectionError(f"{self.port}: read failed: {err}") from err
        if not self._rx:
            return
        if self._last_line and bytes(self._rx) == self._last_line:
            self._rx.clear()
            self.duplicates += 1
            return
        junk = bytes(self._rx[:60])
        self._out_of_step = True
        raise MalformedReplyError(
            f"{self.port}: the drive sent {junk!r} unasked; its last reply may not have "
            "answered the last request"
        )

    def _raw_line(self, deadline: float) -> bytes:
        """One reply line (terminator stripped) or :class:`DriveTimeoutError` at ``deadline``."""
        ser = self._port()
        end = self.dialect.reply_terminator[-1:]
        while True:
            i = self._rx.find(end)
            if i >= 0:
                line = bytes(self._rx[: i + 1])
                del self._rx[: i + 1]
                self._last_line = line
                return line.rstrip(b"\r\n")
            if len(self._rx) > MAX_LINE_BYTES:
                junk = bytes(self._rx[:60])
                self._rx.clear()
                raise DriveConnectionError(f"{self.port}: no line end in {junk!r}... (wrong baud?)")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                partial = f" (partial {bytes(self._rx)!r})" if self._rx else ""
                raise DriveTimeoutError(
                    f"{self.port}: no reply to {' / '.join(self._sent)!r} within "
                    f"{self.reply_timeout_s} s{partial}"
                )
            try:
                ready, _, _ = select.select([ser.fileno()], [], [], remaining)
                if ready:
                    chunk = ser.read(max(1, ser.in_waiting))
                    if not chunk:
                        raise DriveConnectionError(f"{self.port}: port closed by the other end")
                    self._rx += chunk
                    self.bytes_received += len(chunk)
            except (serial.SerialException, OSError) as err:
                raise DriveConnectionError(f"{self.port}: read failed: {err}") from err

    def _read_body(self, deadline: float | None = None) -> str:
        """Next reply body; a rejection message raises :class:`CommandRejectedError`."""
        if deadline is None:
            deadline = time.monotonic() + self.reply_timeout_s
        try:
            body = decode_reply(self._raw_line(deadline), self.use_checksum)
            if self.dialect.rejection(body) is not None:
                raise CommandRejectedError(
                    f"{self.port}: the drive answered {body!r} to {' / '.join(self._sent)!r}"
                )
            return body
        except BaseException:
            self._out_of_step = (
                True  # replies may still be on their way: drain before the next send
            )
            raise
        finally:
            self._sent.clear()  # what was sent before has been answered, or never will be

    def _read_reply(self, name: str) -> ParsedLine:
        body = self._read_body()
        try:
            return self.dialect.parse_reply(name, body)
        except MalformedReplyError:
            self._out_of_step = True
            raise

    def _query(self, command: str, **values: float) -> ParsedLine:
        """Send ``command`` and parse its reply."""
        self._send(self.dialect.request(command, axis=self.axis, **values))
        reply = COMMAND_SPECS[command].reply
        if reply is None:
            raise DriveConfigError(f"dialect command {command!r} has no reply")
        return self._read_reply(reply)

    def _command(self, command: str, **values: float) -> None:
        self._send(self.dialect.request(command, axis=self.axis, **values))

    def _port(self) -> serial.Serial:
        if self._serial is None:
            raise DriveConnectionError(f"{self.port} is not open")
        return self._serial

    def _resync(self, end_drive_line: bool = True) -> None:
        """Drop whatever the drive still sends until it is quiet (after ending its half line)."""
        ser = self._port()
        try:
            ser.reset_input_buffer()
            if end_drive_line:
                ser.write(self.dialect.terminator)
            quiet_until = time.monotonic() + RESYNC_QUIET_S
            give_up = time.monotonic() + RESYNC_MAX_S
            while (remaining := quiet_until - time.monotonic()) > 0:
                if time.monotonic() > give_up:
                    raise DriveConnectionError(
                        f"{self.port}: the drive talks without pause for {RESYNC_MAX_S} s "
                        "(stdout on this port? wrong baud?)"
                    )
                ready, _, _ = select.select([ser.fileno()], [], [], remaining)
                if ready:
                    ser.read(max(1, ser.in_waiting))
                    quiet_until = time.monotonic() + RESYNC_QUIET_S
        except DriveConnectionError:
            raise
        except (serial.SerialException, OSError) as err:
            raise DriveConnectionError(f"{self.port}: resynchronising failed: {err}") from err
        self._rx.clear()
        self._out_of_step = False

    # ------------------------------------------------------------ lifecycle
    def link_recoveries(self) -> dict[str, int]:
        return {"duplicates": self.duplicates}

    def _open(self) -> None:
        try:
            self._serial = serial.Serial(
                self.port, self.baud, timeout=0, write_timeout=WRITE_TIMEOUT_S, exclusive=True
            )
        except (serial.SerialException, OSError, ValueError) as err:
            raise DriveConnectionError(f"cannot open {self.port}: {err}") from err
        try:
            self._resync()
            self._error_code()  # proves the drive speaks the dialect
        except BaseException:
            self._close()
            raise

    def _close(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            finally:
                self._serial = None

    def _configure_watchdog(self, timeout_s: float) -> None:
        self._command("watchdog_timeout", timeout_s=timeout_s)
        self._command("watchdog_feed")  # ODrive: feed before arming, or it trips at once
        self._command("watchdog_enable")
        if self.dialect.has("watchdog_readback"):
            got = self._query("watchdog_readback").fields["timeout_s"]
            if not math.isclose(got, timeout_s, rel_tol=READBACK_RTOL, abs_tol=1e-6):
                raise CommandRejectedError(
                    f"{self.port}: watchdog timeout reads back {got} s, wrote {timeout_s} s"
                )

    def _set_cycle(self, period_s: float) -> None:
        """Tell a lock-step drive the cycle (dialect extension); free-running drives need not know."""
        if not self.dialect.has("set_cycle"):
            self.lockstep = False
            return
        try:
            self._query("cycle_readback")
        except CommandRejectedError:
            self.lockstep = False  # a stock drive: it does not know the extension property
            return
        self._command("set_cycle", period_s=period_s)
        got = self._query("cycle_readback").fields["period_s"]
        if not math.isclose(got, period_s, rel_tol=READBACK_RTOL, abs_tol=1e-6):
            raise CommandRejectedError(f"{self.port}: cycle reads back {got} s, wrote {period_s} s")
        self.lockstep = True

    # ---------------------------------------------------------------- power
    def _state(self) -> int:
        return int(self._query("state").fields["state"])

    def _error_code(self) -> int:
        return int(self._query("error").fields["code"])

    def _raise_fault(self, code: int, doing: str) -> None:
        raise DriveFaultError(
            f"{self.port}: axis {self.axis} {doing}: drive error {self.dialect.describe_error(code)}",
            code,
        )

    def _await_state(self, key: str) -> None:
        target = self.dialect.states[key]
        deadline = time.monotonic() + STATE_TIMEOUT_S
        while True:
            state = self._state()
            if state == target:
                return
            code = self._error_code()
            if code:
                self._raise_fault(code, f"did not become {key}")
            if time.monotonic() > deadline:
                raise StateTransitionError(
                    f"{self.port}: axis {self.axis} state {state}, not {key} ({target}), "
                    f"after {STATE_TIMEOUT_S} s"
                )
            time.sleep(STATE_POLL_S)

    def _enable(self) -> None:
        code = self._error_code()
        if code:
            self._raise_fault(code, "cannot be enabled")
        self._command("torque", u=0.0)  # also selects torque control on an ODrive
        self._command("watchdog_feed")
        self._command("enable")
        self._await_state("enabled")
        self._next_poll = time.monotonic() + self.poll_s

    def _disable(self) -> None:
        self._command("disable")
        self._await_state("disabled")

    def _quick_stop(self) -> None:
        if self.dialect.has("quick_stop"):
            self._command("quick_stop")
        else:
            self._command("torque", u=0.0)

    # --------------------------------------------------------------- cycles
    def _write_command(self, u: float) -> None:
        self._command("torque", u=u)

    def _exchange(self, u: float) -> Feedback:
        d = self.dialect
        lines = [d.request("torque", axis=self.axis, u=u), d.request("feedback", axis=self.axis)]
        now = time.monotonic()
        poll = self.poll_s > 0 and now >= self._next_poll
        if poll:
            lines.append(d.request("error", axis=self.axis))
            self._next_poll = now + self.poll_s
        self._send(*lines)
        fb = self._read_reply("feedback").fields
        t_s = time.monotonic()
        code = int(self._read_reply("error").fields["code"]) if poll else 0
        if code:
            self._raise_fault(code, "faulted while streaming")
        return Feedback(t_s, float(fb["v"]), float(fb["x"]), code)

    def _read_feedback(self) -> Feedback:
        """Position and velocity without clocking the drive (property reads where the dialect has them)."""
        if self.dialect.has("position") and self.dialect.has("velocity"):
            x = float(self._query("position").fields["x"])
            v = float(self._query("velocity").fields["v"])
        else:
            fb = self._query("feedback").fields
            x, v = float(fb["x"]), float(fb["v"])
        t_s = time.monotonic()
        code = self._error_code()
        if code:
            self._raise_fault(code, "is in fault")
        return Feedback(t_s, v, x, code)

    # --------------------------------------------------------------- status
    def _fault_code(self) -> int:
        return self._error_code()

    def _reset_fault(self) -> None:
        self._command("clear_errors")
        code = self._error_code()
        if code:
            self._raise_fault(code, "still in fault after clearing errors")

    def _info(self) -> DriveInfo:
        d = self.dialect
        found: dict[str, str] = {}
        if d.has("info"):
            self._send(d.request("info", axis=self.axis))
            for _ in d.info:
                body = self._read_body()
                for key, template in d.info.items():
                    fields = template.parse(body)
                    if fields is not None:
                        found[key] = str(fields["text"]).strip()
                        break
        extra: dict[str, object] = {
            "dialect": d.name,
            "protocol": f"{d.protocol} (firmware {d.firmware})",
            "reference": d.reference,
            "port": self.port,
            "baud": self.baud,
            "axis": self.axis,
            "checksum": self.use_checksum,
            "lockstep": self.lockstep,
        }
        if found.get("hardware"):
            extra["hardware"] = found["hardware"]
        if d.has("vbus"):
            extra["vbus_V"] = float(self._query("vbus").fields["value"])
        state = self._state()
        names = {v: k for k, v in d.states.items()}
        return DriveInfo(
            transport="serial",
            vendor="",  # the protocol does not tell
            product=found.get("hardware", ""),
            firmware=found.get("firmware", ""),
            serial_number=found.get("serial_number", ""),
            state=names.get(state, f"state {state}"),
            fault_code=self._error_code(),
            units=dict(self.units),
            extra=extra,
        )

"""The line link of ``serial://`` drives: request lines out, reply lines in, in step.

:class:`AsciiLink` owns the serial port of a :class:`~servobench.drivers.serial.drive.SerialAsciiDrive`:
it writes request lines (with the dialect's terminator and, when asked, its
checksum), reads reply lines within a deadline, turns the drive's rejection
texts into :class:`~servobench.drivers.serial.dialect.CommandRejectedError`, and
keeps requests and replies in step.

Before each request the link looks for bytes nobody asked for: an exact
repeat of the last reply line (a duplicated reply) is dropped and counted in
:attr:`AsciiLink.duplicates`; anything else means the last reply may not
have answered the last request, so :class:`MalformedReplyError` is raised
and the line is resynchronised (drained until quiet) before the next request.

Resynchronising at open ends the drive's half line with a bare terminator,
which newer firmware answers with its rejection text (ODrive fw-v0.5.2 on:
``unknown command``). A drive late by more than the quiet window sends that
answer after the drain, ahead of the answer to the first request; so until
the first reply has been read, a rejection is taken for the empty line's and
the reply that follows it for the request's. When none follows by the
deadline, the rejection was the request's own and is raised as such.
POSIX only (waits with ``select`` on the port's file descriptor).
"""

from __future__ import annotations

import select
import time
from collections import deque

import serial

from servobench.drivers.serial.ascii_line import MalformedReplyError, decode_reply, encode_line
from servobench.drivers.serial.dialect import (
    COMMAND_SPECS,
    CommandRejectedError,
    Dialect,
    ParsedLine,
)
from servobench.errors import DriveConfigError, DriveConnectionError, DriveTimeoutError

#: Deadline for a blocked write [s].
WRITE_TIMEOUT_S = 0.5
#: Silence that ends the resynchronisation drain [s].
RESYNC_QUIET_S = 0.05
#: Longest resynchronisation before the drive is deemed to talk nonstop [s].
RESYNC_MAX_S = 1.0
#: Longest reply line accepted [bytes] (the ODrive's transmit buffer is 64).
MAX_LINE_BYTES = 256


class AsciiLink:
    """Request and reply lines of one :class:`Dialect` on a serial port.

    Parameters
    ----------
    port : str
        Device path.
    baud : int
        Bit rate [bit/s].
    dialect : Dialect
        The protocol.
    axis : int
        Axis number filled into the dialect's templates.
    use_checksum : bool
        Append checksums to requests and demand them on replies.
    reply_timeout_s : float
        Deadline of one reply line [s].
    """

    def __init__(
        self, port: str, baud: int, dialect: Dialect, axis: int, use_checksum: bool,
        reply_timeout_s: float,
    ) -> None:  # fmt: skip
        self.port, self.baud, self.dialect, self.axis = port, baud, dialect, axis
        self.use_checksum = use_checksum
        self.reply_timeout_s = reply_timeout_s
        self._serial: serial.Serial | None = None
        self._rx = bytearray()
        self._sent: deque[str] = deque(maxlen=8)  # requests not yet followed by a reply
        self._out_of_step = False
        self._last_line = b""  # the last reply line, terminator included
        self._blank_unanswered = False  # an empty line was sent and no reply read since
        #: Repeated reply lines dropped (see the module docstring).
        self.duplicates = 0
        #: Bytes written to / read from the port since it was opened (for rate figures).
        self.bytes_sent = 0
        self.bytes_received = 0

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def open(self) -> None:
        """Open the port (exclusively) and drain whatever the drive still sends."""
        try:
            self._serial = serial.Serial(
                self.port, self.baud, timeout=0, write_timeout=WRITE_TIMEOUT_S, exclusive=True
            )
        except (serial.SerialException, OSError, ValueError) as err:
            raise DriveConnectionError(f"cannot open {self.port}: {err}") from err
        try:
            self.resync()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Close the port. Safe to call twice."""
        if self._serial is not None:
            try:
                self._serial.close()
            finally:
                self._serial = None

    def send(self, *bodies: str) -> None:
        """Write request lines in one write (after a resync if the last exchange broke off)."""
        ser = self._port()
        if self._out_of_step:
            self.resync(end_drive_line=False)
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
        if self._blank_unanswered and self._is_rejection_line(bytes(self._rx)):
            self._rx.clear()  # the resync's empty line answered late, before any request
            self._blank_unanswered = False
            return
        junk = bytes(self._rx[:60])
        self._out_of_step = True
        raise MalformedReplyError(
            f"{self.port}: the drive sent {junk!r} unasked; its last reply may not have "
            "answered the last request"
        )

    def _is_rejection_line(self, raw: bytes) -> bool:
        """Whether ``raw`` is exactly one whole reply line holding the dialect's rejection."""
        end = self.dialect.reply_terminator[-1:]
        if not raw.endswith(end) or raw.count(end) != 1:
            return False
        try:
            body = decode_reply(raw.rstrip(b"\r\n"), self.use_checksum)
        except MalformedReplyError:
            return False
        return self.dialect.rejection(body) is not None

    def _raw_line(self, deadline: float) -> bytes:
        """One reply line (terminator stripped) or :class:`DriveTimeoutError` at ``deadline``."""
        ser = self._port()
        end = self.dialect.reply_terminator[-1:]
        late = False  # one look past the deadline has been taken
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
            try:
                # past the deadline, look once more without waiting: a host that was descheduled
                # past it finds the reply that came meanwhile, and a drive is silent only when
                # nothing waits in the port
                ready, _, _ = select.select([ser.fileno()], [], [], max(remaining, 0.0))
                chunk = ser.read(max(1, ser.in_waiting)) if ready else None
            except (serial.SerialException, OSError) as err:
                raise DriveConnectionError(f"{self.port}: read failed: {err}") from err
            if ready:
                if not chunk:
                    raise DriveConnectionError(f"{self.port}: port closed by the other end")
                self._rx += chunk
                self.bytes_received += len(chunk)
            if remaining <= 0 and (late or not ready) and self._rx.find(end) < 0:
                partial = f" (partial {bytes(self._rx)!r})" if self._rx else ""
                raise DriveTimeoutError(
                    f"{self.port}: no reply to {' / '.join(self._sent)!r} within "
                    f"{self.reply_timeout_s} s{partial}"
                )
            late = remaining <= 0

    def read_body(self, deadline: float | None = None) -> str:
        """Next reply body; a rejection message raises :class:`CommandRejectedError`."""
        if deadline is None:
            deadline = time.monotonic() + self.reply_timeout_s
        try:
            body = decode_reply(self._raw_line(deadline), self.use_checksum)
            blank, self._blank_unanswered = self._blank_unanswered, False
            rejected = self._rejected(body)
            if rejected is not None and blank:
                try:  # the late answer to the resync's empty line: the request's comes next
                    body = decode_reply(self._raw_line(deadline), self.use_checksum)
                except DriveTimeoutError:
                    raise rejected from None  # none came: the rejection was the request's
                rejected = self._rejected(body)
            if rejected is not None:
                raise rejected
            return body
        except BaseException:
            self._out_of_step = (
                True  # replies may still be on their way: drain before the next send
            )
            raise
        finally:
            self._sent.clear()  # what was sent before has been answered, or never will be

    def _rejected(self, body: str) -> CommandRejectedError | None:
        """The error for a reply ``body`` that is the dialect's rejection text, else ``None``."""
        if self.dialect.rejection(body) is None:
            return None
        return CommandRejectedError(
            f"{self.port}: the drive answered {body!r} to {' / '.join(self._sent)!r}"
        )

    def read_reply(self, name: str) -> ParsedLine:
        body = self.read_body()
        try:
            return self.dialect.parse_reply(name, body)
        except MalformedReplyError:
            self._out_of_step = True
            raise

    def query(self, command: str, **values: float) -> ParsedLine:
        """Send ``command`` and parse its reply."""
        self.send(self.dialect.request(command, axis=self.axis, **values))
        reply = COMMAND_SPECS[command].reply
        if reply is None:
            raise DriveConfigError(f"dialect command {command!r} has no reply")
        return self.read_reply(reply)

    def command(self, command: str, **values: float) -> None:
        self.send(self.dialect.request(command, axis=self.axis, **values))

    def _port(self) -> serial.Serial:
        if self._serial is None:
            raise DriveConnectionError(f"{self.port} is not open")
        return self._serial

    def resync(self, end_drive_line: bool = True) -> None:
        """Drop whatever the drive still sends until it is quiet (after ending its half line)."""
        ser = self._port()
        try:
            ser.reset_input_buffer()
            if end_drive_line:
                ser.write(self.dialect.terminator)
                self._blank_unanswered = True
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
                    chunk = ser.read(max(1, ser.in_waiting))
                    if self.dialect.reply_terminator[-1:] in chunk:
                        self._blank_unanswered = False  # a whole line came: its answer, in time
                    quiet_until = time.monotonic() + RESYNC_QUIET_S
        except DriveConnectionError:
            raise
        except (serial.SerialException, OSError) as err:
            raise DriveConnectionError(f"{self.port}: resynchronising failed: {err}") from err
        self._rx.clear()
        self._out_of_step = False


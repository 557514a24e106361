"""``serial://`` -- drives that speak a line-based ASCII protocol over a serial port.

``serial:///dev/ttyACM0?baud=115200&dialect=odrive`` opens the port with
pyserial and talks the dialect (:mod:`servobench.drivers.serial.dialect`) named by
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
``units``     ``drive`` (default: the drive's own units, turn and turn/s on an ODrive) or
              ``si`` (position and velocity converted by the dialect's ``[units.si]``
              factors, rad and rad/s; the log says so in ``unit_conversion``)

Cycle semantics
---------------
:meth:`Drive.exchange` writes the torque command and the feedback query in
one write and reads the feedback reply: on the lock-step simulator the
command latches and the feedback query clocks one cycle (sample at ``t_k``,
then ``u_k`` acts), which is the :class:`~servobench.drivers.base.Drive` contract. A real
ODrive runs its own loop; there the reply is the latest estimate. Every
``poll`` seconds the error register is read in the same write, and a fault
raises :class:`~servobench.errors.DriveFaultError` with the drive's code.
Feedback ``t_s`` is the host's ``time.monotonic()`` midway between the
query's last byte reaching the drive and its reply's first byte leaving it
(the wire time at ``baud`` taken off both ends; the whole exchange where
the port is faster than that, as USB CDC ports are), with half that interval as
``Feedback.t_unc_s`` (and the midpoint as ``Feedback.t_host_s``) (the protocol carries no drive clock), except on a lock-step drive (one that
took the cycle extension): it integrates exactly one cycle per feedback
query, so its clock is the count of them times the cycle, and
:attr:`SerialAsciiDrive.drive_clock` is True.

Line I/O (terminators, checksums, deadlines, duplicated replies, getting
back in step) is :class:`servobench.drivers.serial.link.AsciiLink`.

Leaving the drive as the firmware expects
------------------------------------------
ODrive firmware 0.5.x checks its axis watchdog in every axis state, idle
included, and the error it sets latches (``Firmware/MotorControl/axis.cpp``,
fw-v0.5.1 to fw-v0.5.6). A watchdog left armed by a host that has gone
therefore faults the idle drive, and the next session cannot enable it. So,
when the dialect has ``watchdog_disable``, the watchdog is armed only while
the axis is enabled: :meth:`open` disarms it (``w axis0.config.enable_watchdog 0``),
reads the firmware version (``r fw_version_major`` / ``minor`` / ``revision``)
and, when the error register holds exactly the watchdog flag
(``WATCHDOG_TIMER_EXPIRED``, 0x800) an earlier session left, clears it and
says so in one line (a :class:`~servobench.errors.DriveWarning`); the timeout
is written and read back; :meth:`enable` refuses a drive in any other fault,
sends ``c 0 0`` (torque control, zero torque), feeds (``u 0``), arms the
watchdog and sends ``w axis0.requested_state 8``, then waits for
``r axis0.current_state`` to read 8 (:class:`~servobench.errors.StateTransitionError`
if it does not, :class:`~servobench.errors.DriveFaultError` with
``axis0.error`` if that is set); :meth:`disable` requests idle, then
disarms; :meth:`close` disarms once more. :meth:`reset_fault` is ``sc`` from
fw-v0.5.2 on; on older firmware, which has no ``sc``, it writes 0 to
``axis0.error``, ``axis0.motor.error``, ``axis0.encoder.error`` and
``axis0.controller.error`` (the dialect's ``[firmware.fallback.clear_errors]``).
:meth:`open` probes the dialect's servobench cycle extension (``r
axis0.config.servobench_cycle``); a drive that rejects it (a stock ODrive) is
free-running (:attr:`SerialAsciiDrive.lockstep` is False) and :meth:`set_cycle`
tells it nothing. The log's ``drive_clock`` line says which clock ``t`` is.

``open(read_only=True)`` (``commission --dry-run``) sends only reads (``r``,
the feedback and identity queries): the watchdog is neither disarmed at open
or close nor fed nor armed, a stale watchdog error is left as it is (and
reported by :meth:`info`), and nothing is configured or commanded (no ``w``,
``c``, ``u`` or ``sc``).

Not confirmed against hardware (no ODrive here; the served simulator follows
the firmware source): see the caveats at the top of
``drivers/data/dialects/odrive.toml`` (firmware 0.6 property names, the
9-character limit of ``r`` replies, the "lu" error-read bug). Without
``checksum=1`` a reply that loses digits, not its line end, still parses
(e.g. ``0.12345`` for ``0.123456``); only checksums catch that.
:meth:`SerialAsciiDrive.max_rate_hz` assumes a UART at ``baud`` (a USB CDC
port is faster than its nominal baud rate).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping
from dataclasses import replace

from servobench.drivers.base import Drive, DriveInfo, Feedback
from servobench.drivers.link_budget import ascii_max_rate_hz
from servobench.drivers.serial.dialect import (
    CommandRejectedError,
    Dialect,
    ParsedLine,
    load_dialect,
)
from servobench.drivers.serial.link import AsciiLink
from servobench.errors import (
    DriveConfigError,
    DriveFaultError,
    DriveWarning,
    StateTransitionError,
    UsageError,
)

DEFAULT_BAUD = 115200
#: Deadline for one reply line [s].
REPLY_TIMEOUT_S = 0.1
#: Deadline for the closed-loop / idle state to be reached [s].
STATE_TIMEOUT_S = 2.0
#: Pause between state reads while waiting for a transition [s].
STATE_POLL_S = 0.005
#: Default period of the error-register read while streaming [s].
FAULT_POLL_S = 0.1
#: Relative tolerance of read-backs (the firmware answers reads with <= 9 characters).
READBACK_RTOL = 1e-3
#: Values that stand for a typical cycle when counting its bytes (command, position, velocity).
TYPICAL_U, TYPICAL_X, TYPICAL_V = -1.234567, -12.345678, -1.234567


class SerialAsciiDrive(Drive):
    """A drive on a serial port speaking a line-based ASCII :class:`~servobench.drivers.serial.dialect.Dialect`."""

    query_keys = frozenset({"baud", "dialect", "axis", "checksum", "timeout", "poll", "units"})

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
        self._scale = self._unit_scales(self.url.get_str("units", "drive"))
        self.link = AsciiLink(
            self.port, self.baud, self.dialect, self.axis, self.use_checksum, self.reply_timeout_s
        )
        #: Whether the drive took the cycle extension at open (False: it runs its own loop).
        self.lockstep: bool | None = None
        #: Firmware (major, minor, revision) read at open; None when the drive does not tell.
        self.firmware_version: tuple[int, ...] | None = None
        #: What open() found and cleared, for the log (empty when nothing).
        self.cleared_at_open = ""
        self._next_poll = 0.0
        self._cycles = 0  # feedback queries since the cycle was set (a lock-step drive's clock)

    def _unit_scales(self, mode: str) -> dict[str, float]:
        """Factors from the drive's position and velocity to the logged ones; sets :attr:`units`."""
        self.units = dict(self.dialect.units)
        if mode == "drive":
            return {"x": 1.0, "v": 1.0}
        if mode != "si":
            raise DriveConfigError(f"units must be 'drive' or 'si', got {mode!r}")
        si = self.dialect.si_units
        if set(si) != {"x", "v"}:
            raise DriveConfigError(f"dialect {self.dialect.name!r} has no [units.si] for x and v")
        for key, (unit, _) in si.items():
            self.units[key] = unit
        return {key: factor for key, (_, factor) in si.items()}

    # ------------------------------------------------------------ link facts
    @property
    def duplicates(self) -> int:
        """Repeated reply lines dropped (see :mod:`servobench.drivers.serial.link`)."""
        return self.link.duplicates

    @property
    def bytes_sent(self) -> int:
        return self.link.bytes_sent

    @property
    def bytes_received(self) -> int:
        return self.link.bytes_received

    def link_recoveries(self) -> dict[str, int]:
        return {"duplicates": self.duplicates}

    def max_rate_hz(self) -> float:
        """The exchange rate the UART carries: a torque command and a feedback query out, the
        feedback reply in, every ``poll`` seconds an error read too (8N1 at ``baud``)."""
        d, ax = self.dialect, self.axis
        term, reply_term = len(d.terminator), len(d.reply_terminator)
        request = [d.request("torque", axis=ax, u=TYPICAL_U), d.request("feedback", axis=ax)]
        reply = d.reply("feedback", x=TYPICAL_X, v=TYPICAL_V)
        poll_out = len(d.request("error", axis=ax)) + term
        poll_in = len(d.reply("error", code=0)) + reply_term
        return ascii_max_rate_hz(
            sum(len(r) + term for r in request) + len(reply) + reply_term,
            self.baud,
            poll_bytes=poll_out + poll_in,
            poll_s=self.poll_s,
        )

    def command_lead_s(self) -> float:
        """A free-running drive latches the torque line before the feedback query arrives:
        the query's wire time at ``baud`` (10 bits a character)."""
        if self.lockstep or self.lockstep is None:
            return 0.0
        d, extra = self.dialect, (3 if self.use_checksum else 0)
        return (len(d.request("feedback", axis=self.axis)) + len(d.terminator) + extra) * 10.0 / self.baud

    def clock_source(self) -> str:
        """``drive`` for a lock-step drive (its cycle count), else ``host`` (query to reply)."""
        return "drive" if self.lockstep else "host"

    def log_metadata(self) -> dict[str, str]:
        meta = super().log_metadata()
        if self.lockstep is not None:
            meta["drive_clock"] = (
                "feedback query count x cycle period (lock-step drive)" if self.lockstep
                else "none: host reception time (the drive runs its own loop)"
            )  # fmt: skip
        if self._scale["x"] != 1.0 or self._scale["v"] != 1.0:
            own = self.dialect.units
            meta["unit_conversion"] = (
                f"by the host (units=si): x {own['x']} -> {self.units['x']} "
                f"(* {self._scale['x']:.9g}), v {own['v']} -> {self.units['v']} "
                f"(* {self._scale['v']:.9g})"
            )
        if self.firmware_version is not None:
            meta["drive_firmware"] = ".".join(map(str, self.firmware_version))
        if self.cleared_at_open:
            meta["cleared_at_open"] = self.cleared_at_open
        return meta

    # ------------------------------------------------------------ line helpers
    def _query(self, command: str, **values: float) -> ParsedLine:
        return self.link.query(command, **values)

    def _command(self, command: str, **values: float) -> None:
        if self.read_only:  # the last guard: nothing above should have come here
            raise UsageError(f"{self.port} was opened read-only: refused to send {command!r}")
        self.link.command(command, **values)

    # ------------------------------------------------------------ lifecycle
    def _open(self) -> None:
        self.link.open()
        try:
            code = self._error_code()  # proves the drive speaks the dialect
            if not self.read_only:
                self._disarm()  # a watchdog an earlier host left armed would fault the idle axis
            self.firmware_version = self._read_version()
            self.lockstep = self._has_cycle_extension()
            if code and code == self.dialect.watchdog_error and not self.read_only:
                self._clear_stale_watchdog(code)
        except BaseException:
            self.link.close()
            raise

    def _read_version(self) -> tuple[int, ...] | None:
        """(major, minor, revision) from the dialect's version reads; None if the drive refuses them."""
        if not self.dialect.version_requests:
            return None
        parts = []
        try:
            for body in self.dialect.version_requests:
                self.link.send(body)
                parts.append(int(float(self.link.read_body())))
        except (CommandRejectedError, ValueError):
            return None
        return tuple(parts)

    def _clear_stale_watchdog(self, code: int) -> None:
        """Clear the lone watchdog error an earlier session left, and say so in one line."""
        self._send_clear_errors()
        after = self._error_code()
        if after:
            return  # still set: enable() refuses with the code
        what = self.dialect.describe_error(code)
        self.cleared_at_open = what
        warnings.warn(
            DriveWarning(
                f"{self.port}: axis {self.axis} held {what} from an earlier session "
                "(its watchdog was left armed); cleared"
            ),
            stacklevel=4,
        )

    def _disarm(self) -> None:
        if self.dialect.has("watchdog_disable"):
            self._command("watchdog_disable")

    def _close(self) -> None:
        try:
            if self.link.is_open and not self.read_only:
                self._disarm()
        finally:
            self.link.close()

    def _configure_watchdog(self, timeout_s: float) -> None:
        self._command("watchdog_timeout", timeout_s=timeout_s)
        if not self.dialect.has("watchdog_disable"):  # cannot be disarmed: armed for good now
            self._command("watchdog_feed")  # ODrive: feed before arming, or it trips at once
            self._command("watchdog_enable")
        if self.dialect.has("watchdog_readback"):
            got = self._query("watchdog_readback").fields["timeout_s"]
            if not math.isclose(got, timeout_s, rel_tol=READBACK_RTOL, abs_tol=1e-6):
                raise CommandRejectedError(
                    f"{self.port}: watchdog timeout reads back {got} s, wrote {timeout_s} s"
                )

    def _has_cycle_extension(self) -> bool:
        """True when the drive knows the dialect's cycle extension (a lock-step simulator)."""
        if not (self.dialect.has("set_cycle") and self.dialect.has("cycle_readback")):
            return False
        try:
            self._query("cycle_readback")
        except CommandRejectedError:
            return False  # a stock drive: it does not know the extension property
        return True

    def _set_cycle(self, period_s: float) -> None:
        """Tell a lock-step drive the cycle (dialect extension); free-running drives need not know."""
        if not self.lockstep:
            return
        self._command("set_cycle", period_s=period_s)
        got = self._query("cycle_readback").fields["period_s"]
        if not math.isclose(got, period_s, rel_tol=READBACK_RTOL, abs_tol=1e-6):
            raise CommandRejectedError(f"{self.port}: cycle reads back {got} s, wrote {period_s} s")
        self.drive_clock = True  # one cycle per feedback query: the count is its clock
        self._cycles = 0

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
            if self.dialect.has("watchdog_disable"):
                self._command("watchdog_feed")  # armed while enabling: the wait must feed it
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
        if self.dialect.has("watchdog_disable"):
            self._command("watchdog_enable")  # armed while the axis has torque
        self._command("enable")
        self._await_state("enabled")
        self._next_poll = time.monotonic() + self.poll_s

    def _disable(self) -> None:
        self._command("disable")
        try:
            self._await_state("disabled")
        finally:
            self._disarm()

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
        sent = time.monotonic()
        self.link.send(*lines)
        fb = self.link.read_reply("feedback").fields
        received = time.monotonic()
        t_count = self._now()  # the lock-step clock of this sample, before it counts the cycle
        self._cycles += 1
        code = int(self.link.read_reply("error").fields["code"]) if poll else 0
        if code:
            self._raise_fault(code, "faulted while streaming")
        if self.lockstep and self.cycle_s is not None:
            return self._feedback(t_count, float(fb["v"]), float(fb["x"]), code)
        lo, hi = self._sample_window(sent, received, lines[:2], fb)
        mid = 0.5 * (lo + hi)
        fb_ = self._feedback(mid, float(fb["v"]), float(fb["x"]), code)
        return replace(fb_, t_host_s=mid, t_unc_s=0.5 * (hi - lo))

    def _sample_window(
        self, sent: float, received: float, requests: list[str], fb: Mapping[str, float]
    ) -> tuple[float, float]:
        """Host instants [s] between which a free-running drive sampled.

        The query cannot be handled before its last byte arrived, nor the
        reply leave after its first byte had to: on a UART at ``baud`` (10 bits
        a character) the interval shrinks by the request's and the reply's
        wire time. A link faster than that (a USB CDC port) leaves no interval
        between them: then the whole exchange.
        """
        d, extra = self.dialect, (3 if self.use_checksum else 0)
        char_s = 10.0 / self.baud
        out = sum(len(r) + len(d.terminator) + extra for r in requests)
        back = len(d.reply("feedback", x=float(fb["x"]), v=float(fb["v"]))) + len(d.reply_terminator) + extra
        lo, hi = sent + out * char_s, received - back * char_s
        return (lo, hi) if lo < hi else (sent, received)

    def _now(self) -> float:
        """Sample time [s]: the lock-step drive's cycle count times the cycle, else host time."""
        if self.lockstep and self.cycle_s is not None:
            return self._cycles * self.cycle_s
        return time.monotonic()

    def _feedback(self, t_s: float, v: float, x: float, code: int) -> Feedback:
        return Feedback(t_s, v * self._scale["v"], x * self._scale["x"], code)

    def _read_feedback(self) -> Feedback:
        """Position and velocity without clocking the drive (property reads where the dialect has them)."""
        t_s = self._now()
        if self.dialect.has("position") and self.dialect.has("velocity"):
            x = float(self._query("position").fields["x"])
            v = float(self._query("velocity").fields["v"])
        else:  # the feedback query clocks a lock-step drive: sampled at t_k
            fb = self._query("feedback").fields
            x, v = float(fb["x"]), float(fb["v"])
            self._cycles += 1
        code = self._error_code()
        if code:
            self._raise_fault(code, "is in fault")
        return self._feedback(t_s, v, x, code)

    # --------------------------------------------------------------- status
    def _fault_code(self) -> int:
        return self._error_code()

    def _send_clear_errors(self) -> None:
        if self.read_only:
            raise UsageError(f"{self.port} was opened read-only: refused to clear its errors")
        bodies = self.dialect.requests("clear_errors", self.firmware_version, axis=self.axis)
        self.link.send(*bodies)

    def _reset_fault(self) -> None:
        self._send_clear_errors()
        code = self._error_code()
        if code:
            self._raise_fault(code, "still in fault after clearing errors")

    def _info(self) -> DriveInfo:
        d = self.dialect
        found: dict[str, str] = {}
        if d.has("info"):
            self.link.send(d.request("info", axis=self.axis))
            for _ in d.info:
                body = self.link.read_body()
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

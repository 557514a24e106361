"""The transport-agnostic :class:`Drive` interface.

Every backend (``sim``, ``canopen``, ``modbus+tcp``, ``modbus+rtu``,
``serial``) subclasses :class:`Drive` and implements a handful of small
``_internal`` hooks; the public methods here own what must be the same on
every transport: the safety envelope (command clamping, velocity and travel
limits), the lifecycle (a context manager whose exit stops and disables the
axis, ``close()`` safe to call twice) and the cycle semantics.

Sign and sampling conventions
-----------------------------
* Command ``u`` is in the drive's command units (torque, current or voltage,
  as the backend documents); positive ``u`` accelerates towards positive
  velocity.
* One control cycle ``k`` is :meth:`Drive.exchange`: the feedback returned is
  sampled at ``t_k``, *before* ``u_k`` acts, and ``u_k`` is then held over
  ``[t_k, t_{k+1})`` (zero-order hold).
"""

from __future__ import annotations

import math
import warnings
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from servobench.drivers.url import DriveURL, parse_drive_url
from servobench.errors import (
    DriveConnectionError,
    DriveError,
    DriveUnavailableError,
    LimitExceededError,
    UsageError,
)

#: Query keys every backend accepts: the safety envelope, the watchdog, and the
#: host pacing (``pace=real``: the host holds the cycle rate, the default;
#: ``pace=fast``: as fast as the link answers, for lock-step simulated drives).
COMMON_QUERY_KEYS = frozenset({"max_u", "max_v", "xmin", "xmax", "watchdog", "pace"})

#: Values of :meth:`Drive.clock_source` (the log's ``# clock_source`` line).
CLOCK_SOURCES = ("drive", "kernel", "host")

#: Drive-side watchdog used when the URL does not set one [s].
DEFAULT_WATCHDOG_S = 0.5


@dataclass(frozen=True)
class Limits:
    """Safety envelope enforced by the Drive layer on every transport.

    Attributes
    ----------
    max_command : float
        Largest ``|u|`` sent to the drive [command units]; larger commands are clamped.
    max_velocity : float
        Largest allowed ``|v|`` [velocity units/s]; beyond it the axis is stopped.
    min_position, max_position : float
        Allowed travel [position units]; outside it the axis is stopped.
    """

    max_command: float = math.inf
    max_velocity: float = math.inf
    min_position: float = -math.inf
    max_position: float = math.inf

    def __post_init__(self) -> None:
        if not self.max_command > 0 or not self.max_velocity > 0:
            raise UsageError("max_u and max_v must be > 0")
        if not self.min_position < self.max_position:
            raise UsageError("xmin must be below xmax")

    def clamp(self, u: float) -> float:
        """``u`` limited to ``[-max_command, max_command]``."""
        return min(max(u, -self.max_command), self.max_command)

    def violation(self, velocity: float, position: float) -> str | None:
        """A sentence naming the envelope breach, or ``None`` when inside."""
        if not abs(velocity) <= self.max_velocity:
            return f"|velocity| {abs(velocity):.4g} exceeds the limit {self.max_velocity:.4g}"
        if not self.min_position <= position <= self.max_position:
            return (
                f"position {position:.4g} outside the allowed travel "
                f"[{self.min_position:.4g}, {self.max_position:.4g}]"
            )
        return None

    def as_dict(self) -> dict[str, float]:
        return {
            "max_u": self.max_command,
            "max_v": self.max_velocity,
            "xmin": self.min_position,
            "xmax": self.max_position,
        }


@dataclass(frozen=True)
class Feedback:
    """One feedback sample.

    Attributes
    ----------
    t_s : float
        Sample time [s]: the drive's clock when the transport carries one,
        otherwise the host's ``time.monotonic()`` at reception.
    velocity : float
        Velocity [velocity units/s], positive in the direction of positive command.
    position : float
        Position [position units].
    fault_code : int
        Drive fault code, 0 when the drive is healthy.
    applied : float
        The command the drive reports it applied over the previous cycle
        [command units] (CiA 402 torque actual value 0x6077), NaN when the
        transport does not report one. Under a drive-side position hold it is
        the total of the drive's loop and the host's offset.
    t_host_s, t_unc_s : float
        The sample's instant on the host's ``time.monotonic()`` clock and the
        half-width of the interval known to hold it [s], where the transport
        narrows it to the one transaction that sampled (Modbus: the clocking
        read; serial: query out to reply in; CANopen: SYNC out to TPDOs in,
        or the kernel's SYNC timer on SocketCAN). NaN: not narrowed, and a
        real-time runner brackets the whole exchange. Used where the drive
        gives no time stamp of its own (:meth:`Drive.clock_source`).
    t_act_s : float
        The instant the command sent with this exchange took force [s, on the
        clock of ``t_s``], where the transport knows it
        (:meth:`Drive.reports_action_instant`): the sample's own instant when
        all went to plan; earlier where the sample returned is a later tick's
        than the one the command acted from (an EtherCAT DC-synchronous
        slave whose inputs were read a cycle or more after the SYNC0 event
        that latched the command: a host that woke late). NaN: not known, the
        command acts from the sample's instant as :meth:`Drive.exchange` says.
    """

    t_s: float
    velocity: float
    position: float
    fault_code: int = 0
    applied: float = math.nan
    t_host_s: float = math.nan
    t_unc_s: float = math.nan
    t_act_s: float = math.nan


@dataclass(frozen=True)
class BlockFeedback:
    """Feedback of a block of cycles, one entry per cycle (arrays of shape ``(n,)``)."""

    t_s: np.ndarray
    velocity: np.ndarray
    position: np.ndarray
    applied: np.ndarray


@dataclass(frozen=True)
class DriveInfo:
    """Identity and state of a drive, as far as the protocol tells."""

    transport: str
    vendor: str = ""
    product: str = ""
    firmware: str = ""
    serial_number: str = ""
    state: str = ""
    fault_code: int = 0
    units: Mapping[str, str] = field(default_factory=dict)
    extra: Mapping[str, Any] = field(default_factory=dict)


class Drive(ABC):
    """A servo drive on some transport.

    Subclasses implement ``_open``, ``_close``, ``_enable``, ``_disable``,
    ``_write_command`` and ``_read_feedback``; they may override ``_exchange``
    (one atomic cycle, e.g. SYNC + PDOs or Modbus FC23), ``_exchange_block``,
    ``_quick_stop``, ``_configure_watchdog``, ``_set_cycle``, ``_fault_code``,
    ``_reset_fault`` and ``_info``. Optional capabilities are declared here
    with their defaults (:attr:`realtime`, :attr:`supports_block`,
    :attr:`supports_drive_hold`, :attr:`hold_only`, :attr:`remarks`, :attr:`read_only`,
    :meth:`max_rate_hz`, :meth:`log_metadata`, :meth:`link_recoveries`,
    :meth:`record_traffic`, :meth:`clock_source`, :meth:`io_threads`, :meth:`start_cycle_clock`),
    never probed.

    Parameters
    ----------
    url : DriveURL or str
        The drive URL; its query may hold ``max_u``, ``max_v``, ``xmin``,
        ``xmax`` (the :class:`Limits`) and ``watchdog`` [s], plus the keys in
        the backend's :attr:`query_keys`.
    """

    #: Backend-specific query keys, beyond :data:`COMMON_QUERY_KEYS`.
    query_keys: ClassVar[frozenset[str]] = frozenset()
    #: True when ``Feedback.t_s`` is the drive's own sample clock (not host reception time).
    drive_clock: ClassVar[bool] = False
    #: True when the drive runs in wall-clock time, as hardware does; False for a
    #: lock-step simulation that advances one cycle per exchange (the runner then
    #: streams it as fast as it answers unless the URL says ``pace=real``).
    realtime: bool = True
    #: True when :meth:`exchange_block` is faster than per-cycle exchange.
    supports_block: bool = False
    #: True when the drive can hold a position with its own loop while the host's
    #: command is added as a torque offset (CiA 402 cyclic synchronous position
    #: with 0x60B2); see :meth:`hold_position`.
    supports_drive_hold: bool = False
    #: True when the drive takes a command only as the torque offset of its own
    #: position hold (a CiA 402 drive without cyclic synchronous torque, or one
    #: told ``mode=csp``): enabling holds the position it stands at, and a run must
    #: excite it under :meth:`hold_position` (the closed-loop path), where
    #: ``Feedback.applied`` is the total command. Implies :attr:`supports_drive_hold`.
    hold_only: bool = False
    #: Units of command, velocity and position, keys ``u``, ``v``, ``x``: SI as
    #: ``"N m"``, ``"N"``, ``"A"``, ``"rad/s"``, ``"m/s"``, ``"rad"``, ``"m"``, else
    #: the drive's own unit named as such (``"rpm"``, ``"inc"``); ``""`` when
    #: unknown. A backend may refine them at :meth:`open` from what the drive reports.
    units: Mapping[str, str] = {"u": "", "v": "", "x": ""}

    def __init__(self, url: DriveURL | str) -> None:
        self.url = parse_drive_url(url) if isinstance(url, str) else url
        self.url.check_keys(COMMON_QUERY_KEYS | self.query_keys)
        self.limits = Limits(
            max_command=self.url.get_float("max_u", math.inf),
            max_velocity=self.url.get_float("max_v", math.inf),
            min_position=self.url.get_float("xmin", -math.inf),
            max_position=self.url.get_float("xmax", math.inf),
        )
        self.watchdog_s: float = self.url.get_float("watchdog", DEFAULT_WATCHDOG_S)
        if not self.watchdog_s > 0:
            raise UsageError("watchdog must be > 0 s")
        self.cycle_s: float | None = None
        #: What the drive did otherwise than asked, one sentence each (an optional object it
        #: refused, a stop it did not honour); in :meth:`log_metadata` as ``remarks``.
        self.remarks: list[str] = []
        self._read_only = False
        self._is_open = False
        self._enabled = False
        self._holding = False

    # ----------------------------------------------------------------- lifecycle
    @property
    def is_open(self) -> bool:
        return self._is_open

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def read_only(self) -> bool:
        """True when opened with ``read_only``: nothing is written to the drive."""
        return self._read_only

    def open(self, *, read_only: bool = False) -> Drive:
        """Connect and arm the drive-side watchdog. Idempotent.

        ``read_only``: only read (identity, state, faults, feedback); nothing is
        written to the drive, no watchdog is armed and no bus state beyond what
        reading needs is requested (EtherCAT stays in PRE-OP, CANopen gets no NMT
        command). Backends see it as :attr:`read_only` in ``_open``. A read-only
        drive refuses :meth:`enable`, commands and set-up; :meth:`stop` and
        :meth:`disable` have nothing to do.
        """
        if not self._is_open:
            self._read_only = bool(read_only)
            self._open()
            self._is_open = True
            if self._read_only:
                return self
            try:
                self._configure_watchdog(self.watchdog_s)
            except BaseException:
                self.close()
                raise
        return self

    def _require_writable(self) -> None:
        self._require_open()
        if self._read_only:
            raise UsageError(f"the {self.url.scheme} drive was opened read-only: it takes no command")

    def close(self) -> None:
        """Stop and disable the axis, then disconnect. Safe to call twice."""
        if not self._is_open:
            return
        try:
            if self._enabled:
                try:
                    self.stop()
                finally:
                    self.disable()
        finally:
            self._is_open = False
            self._close()

    def __enter__(self) -> Drive:
        return self.open()

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        if exc is None:
            self.close()
            return
        try:
            self.close()
        except Exception as err:  # the error that ended the block matters more
            if hasattr(exc, "add_note") and not _link_lost(exc):  # Python >= 3.11
                exc.add_note(f"closing the drive also failed: {err}")
        if not _link_lost(exc):
            return
        state = (f"no stop could reach the axis: the drive-side watchdog armed at open stops it within "
                 f"{self.watchdog_s:g} s of silence; check that it stands before the next run")  # fmt: skip
        if isinstance(exc, DriveError):  # worded by the driver already: keep its type, add the state
            if hasattr(exc, "add_note"):  # Python >= 3.11
                exc.add_note(state)
            return
        where = self.url.raw.split("?", 1)[0]
        why = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
        raise DriveConnectionError(f"lost the link to the drive {where} ({why}); {state}") from exc

    def __del__(self) -> None:
        if getattr(self, "_is_open", False):
            warnings.warn(f"{type(self).__name__} was never closed", ResourceWarning, stacklevel=1)

    def _require_open(self) -> None:
        if not self._is_open:
            raise DriveError(f"{self.url.scheme} drive is not open")

    # ------------------------------------------------------------------- power
    def enable(self) -> None:
        """Bring the drive to its operational (torque-on) state with zero command."""
        self._require_writable()
        self._enable()
        self._enabled = True

    def disable(self) -> None:
        """Remove torque (zero command first). Safe when already disabled."""
        if not self._is_open or self._read_only:
            return
        try:
            self._write_command(0.0)
        except DriveError:
            pass  # disabling is what matters; the command path may be the broken part
        finally:
            self._enabled = False
            self._holding = False
            self._disable()

    def stop(self) -> None:
        """Quick stop: zero command and the drive's own stop ramp where it has one.

        A drive that does not honour its quick stop is brought to a safe state
        another way by the backend (CiA 402: disable voltage), which says so in
        :attr:`remarks`; only an axis that could not be stopped at all raises.
        Nothing to do on a drive opened read-only (it was never enabled).
        """
        self._require_open()
        if self._read_only:
            return
        self._quick_stop()

    @property
    def holding(self) -> bool:
        """True while the drive's own loop holds a position (:meth:`hold_position`)."""
        return self._holding

    def hold_position(self, x_ref: float) -> None:
        """Let the drive's own position loop hold ``x_ref`` [position units].

        From then on :meth:`exchange` adds its command to the output of the
        drive's loop as a torque offset (still clamped to ``max_u``), and
        ``Feedback.applied`` reports the total command the drive applied. The
        hold ends with :meth:`release_hold`, :meth:`disable` or :meth:`close`.

        Raises
        ------
        DriveUnavailableError
            The drive has no such mode (:attr:`supports_drive_hold` is False).
        """
        self._require_writable()
        if not self.supports_drive_hold:
            raise DriveUnavailableError(
                f"{self.url.scheme}:// cannot hold a position with its own loop; "
                "use the host-side hold loop"
            )
        self._hold_position(float(x_ref))
        self._holding = True

    def release_hold(self) -> None:
        """Leave the drive-side hold: back to plain command mode with zero command."""
        self._require_open()
        if self._holding:
            try:
                self._release_hold()
            finally:
                self._holding = False

    def set_cycle(self, period_s: float) -> None:
        """Tell the drive the control cycle period [s] the host will stream at."""
        if not period_s > 0:
            raise UsageError("cycle period must be > 0 s")
        if self._read_only:
            self._require_writable()
        self.cycle_s = float(period_s)
        self._set_cycle(self.cycle_s)

    # ----------------------------------------------------------------- cycles
    def command(self, u: float) -> float:
        """Send command ``u`` (clamped to the limits); return the value applied."""
        self._require_writable()
        applied = self._representable(self.limits.clamp(float(u)))
        self._write_command(applied)
        return applied

    def read(self) -> Feedback:
        """Read one feedback sample; stop the axis if it is outside the envelope."""
        self._require_open()
        return self._checked(self._read_feedback())

    def exchange(self, u: float) -> tuple[Feedback, float]:
        """One control cycle: feedback sampled at ``t_k``, then ``u`` held until ``t_{k+1}``.

        Returns the feedback and the command actually applied (after clamping).
        """
        self._require_writable()
        applied = self._representable(self.limits.clamp(float(u)))
        return self._checked(self._exchange(applied)), applied

    def exchange_block(self, u: np.ndarray) -> BlockFeedback:
        """Several cycles at once (fast simulated drives); same semantics as :meth:`exchange`."""
        self._require_writable()
        u = np.asarray(u, dtype=float)
        applied = np.clip(u, -self.limits.max_command, self.limits.max_command)
        block = self._exchange_block(applied)
        bad = np.flatnonzero(
            (np.abs(block.velocity) > self.limits.max_velocity)
            | (block.position < self.limits.min_position)
            | (block.position > self.limits.max_position)
        )
        if bad.size:
            i = int(bad[0])
            try:
                self._checked(Feedback(block.t_s[i], block.velocity[i], block.position[i]))
            except LimitExceededError as err:
                head = slice(0, i + 1)
                err.partial = BlockFeedback(
                    block.t_s[head], block.velocity[head], block.position[head], block.applied[head]
                )
                raise
        return block

    def _checked(self, fb: Feedback) -> Feedback:
        breach = self.limits.violation(fb.velocity, fb.position)
        if breach is not None:
            try:
                self.stop()
            finally:
                self.disable()
            raise LimitExceededError(f"axis stopped: {breach}")
        return fb

    # ---------------------------------------------------------------- status
    def fault_code(self) -> int:
        """The drive's active fault code, 0 when healthy."""
        self._require_open()
        return self._fault_code()

    def reset_fault(self) -> None:
        """Acknowledge a drive fault; raises :class:`DriveFaultError` if it persists."""
        self._require_writable()
        self._reset_fault()

    def info(self) -> DriveInfo:
        """Identity, firmware and state as far as the protocol tells."""
        self._require_open()
        return self._info()

    def max_rate_hz(self) -> float:
        """Highest cycle rate [Hz] this link and drive sustain, one exchange per cycle.

        From the link's wire budget (:mod:`servobench.drivers.link_budget`) and
        the drive's own limits; ``inf`` when nothing bounds it (the default,
        and the in-process simulated drive). The runner picks its default
        sample rate within it and refuses an explicit rate beyond it.
        """
        return math.inf

    def rate_limit_reason(self) -> str:
        """What bounds :meth:`max_rate_hz`, in a few words for the terminal (``""``: nothing to add)."""
        return ""

    def log_metadata(self) -> dict[str, str]:
        """``# key = value`` lines this drive contributes to every log streamed from it.

        The base gives the signal units ``unit_u``, ``unit_v``, ``unit_x`` (from
        :attr:`units`; unknown ones are left out) and ``link_max_rate_hz`` where
        :meth:`max_rate_hz` is finite. Backends add what a reader of the log
        must know, such as where each scale factor came from or what the drive
        clock is.
        """
        meta = {f"unit_{k}": v for k, v in self.units.items() if k in ("u", "v", "x") and v}
        rate_hz = self.max_rate_hz()
        if math.isfinite(rate_hz):
            meta["link_max_rate_hz"] = f"{rate_hz:.1f}"
        if self.remarks:
            meta["remarks"] = "; ".join(self.remarks)
        return meta

    def clock_source(self) -> str:
        """Where the instant of each sample comes from when streamed in real time.

        One of :data:`CLOCK_SOURCES` (a log contract, ``# clock_source``):

        * ``"drive"`` -- ``Feedback.t_s`` is the drive's own time stamp of the
          sample (CiA 402 0x1013, a Modbus map's time-stamp register, a
          lock-step drive's cycle count);
        * ``"kernel"`` -- the kernel's time of a frame (SocketCAN receive
          stamps, a SYNC the kernel sends on its own timer);
        * ``"host"`` -- the host's clock bracketing the exchange.

        Default: ``"drive"`` when :attr:`drive_clock`, else ``"host"``.
        """
        return "drive" if self.drive_clock else "host"

    def command_lead_s(self) -> float:
        """How long before its sample the command of the same exchange takes force [s].

        0 (the default) where the drive samples and applies in one instant (a
        SYNC with synchronous RPDOs, one FC23 request, a lock-step drive). A
        transport that sends the command and the feedback query one after the
        other on a free-running drive states the gap (the query's wire time):
        the runner logs it as ``# command_lead_s`` and the identification lets the
        drive's action delay reach down to ``-command_lead_s`` (the command acts
        before its logged instant where the drive has no tick of its own).
        """
        return 0.0

    def reports_action_instant(self) -> bool:
        """True where each exchange's :attr:`Feedback.t_act_s` says when its command took force.

        A real-time runner then logs it as the column ``t_act`` (the instant
        each row's command acted from, on the clock of ``t``), and the
        identification moves each row's action there: a command that acted a
        tick before its row's sample is not taken to act a tick late. Default
        False: every command acts from its sample's instant.
        """
        return False

    def io_threads(self) -> tuple[int, ...]:
        """Native ids of the threads an exchange waits on (a CAN library's receive thread).

        The runner's cyclic thread gives them real-time priority just below
        its own for the run. Default: none (the exchange reads in the calling thread).
        """
        return ()

    def start_cycle_clock(self, period_s: float) -> bool:
        """Let the transport time the cycle itself, where it can, for a real-time run.

        True when it does from now on (SocketCAN: the SYNC sent by the
        kernel's broadcast manager every ``period_s``): :meth:`exchange` then
        waits for the next cycle and the host holds no schedule of its own.
        Default: False, the host paces. :meth:`stop_cycle_clock` ends it.
        """
        return False

    def stop_cycle_clock(self) -> None:
        """End what :meth:`start_cycle_clock` started; safe when nothing was started."""
        return None

    def cycle_counts(self) -> Mapping[str, int]:
        """Cycle faults the transport counted during a :meth:`start_cycle_clock` run, by kind
        (``{"late_rpdos": n, "missed_syncs": m}``); empty by default."""
        return {}

    def link_recoveries(self) -> Mapping[str, int]:
        """Transport-level recoveries counted since the drive was created, by kind.

        ``{"retries": n}`` for a link that re-sent a request the drive answered
        busy, ``{"duplicates": n}`` for one that dropped repeated replies; empty
        (the default) for links that count none. The runner writes the non-zero
        counts into the log trailer as ``link_<kind>``.
        """
        return {}

    def record_traffic(self, path: str) -> None:
        """Record the raw bus traffic to ``path`` until :meth:`close`.

        CAN backends write python-can logger formats chosen by the suffix
        (candump ``.log``, ``.blf``, ``.asc``, ``.csv``); other transports raise
        :class:`DriveUnavailableError`.
        """
        self._require_open()
        self._record_traffic(path)

    # --------------------------------------------------------- backend hooks
    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _close(self) -> None: ...

    @abstractmethod
    def _enable(self) -> None: ...

    @abstractmethod
    def _disable(self) -> None: ...

    @abstractmethod
    def _write_command(self, u: float) -> None: ...

    @abstractmethod
    def _read_feedback(self) -> Feedback: ...

    def _exchange(self, u: float) -> Feedback:
        fb = self._read_feedback()
        self._write_command(u)
        return fb

    def _exchange_block(self, u: np.ndarray) -> BlockFeedback:
        rows = [self._exchange(float(uk)) for uk in u]
        return BlockFeedback(
            t_s=np.array([r.t_s for r in rows]),
            velocity=np.array([r.velocity for r in rows]),
            position=np.array([r.position for r in rows]),
            applied=u.copy(),
        )

    def _quick_stop(self) -> None:
        self._write_command(0.0)

    def _representable(self, u: float) -> float:
        """The command nearest ``u`` that the drive can represent (its command resolution).

        The default is ``u`` itself; a backend whose command travels as an
        integer (CiA 402 per-mille torque) rounds here, so that the command
        returned as applied, and logged, is the one the drive received.
        """
        return u

    def _hold_position(self, x_ref: float) -> None:
        raise NotImplementedError(f"{type(self).__name__} declares a drive-side hold but has none")

    def _release_hold(self) -> None:
        raise NotImplementedError(f"{type(self).__name__} declares a drive-side hold but has none")

    def _configure_watchdog(self, timeout_s: float) -> None:
        raise NotImplementedError(f"{type(self).__name__} has no drive-side watchdog")

    def _set_cycle(self, period_s: float) -> None:
        """Default: the drive needs no notice of the host's cycle."""
        return None

    def _fault_code(self) -> int:
        return 0

    def _reset_fault(self) -> None:
        """Default: nothing to acknowledge."""
        return None

    def _info(self) -> DriveInfo:
        return DriveInfo(transport=self.url.scheme, units=dict(self.units))

    def _record_traffic(self, path: str) -> None:
        raise DriveUnavailableError(
            f"{self.url.scheme}:// cannot record bus traffic (python-can formats are for CAN links)"
        )


def _link_lost(exc: BaseException) -> bool:
    """True for a transport's connection error (reset, broken pipe, refused, aborted): a socket
    error the drive layer did not word, or its own :class:`DriveConnectionError`."""
    return isinstance(exc, ConnectionError) and not getattr(exc, "filename", None)

"""What an ``ethercat://`` URL says besides the safety keys.

``ethercat://IFACE?slave=N&dc=auto&frame_timeout=0.05&max_wkc_errors=10``

``IFACE`` the network interface of the EtherCAT segment (or ``iface=`` when
its name cannot be a URL host); ``slave`` the position on the bus, 1 the
first slave (as SOEM counts), default 1; ``dc`` ``auto`` (SYNC0 where the slave
has distributed clocks, default), ``on`` (required) or ``off``;
``frame_timeout`` [s] how long a process data frame may take to come back
(default 0.1: "the slave answered" on a loaded host); ``max_wkc_errors``
frames in a row lost or with a wrong working counter (each is sent again)
before the link counts as lost (default 10); ``pos_scale``, ``vel_scale``,
``torque_constant`` override the factor group as on CANopen
(:mod:`servobench.drivers.cia402_units`); ``mode`` how the drive is
commanded: ``cst`` cyclic synchronous torque (target torque 0x6071),
``csp`` the torque offset 0x60B2 under the drive's own cyclic synchronous
position hold (``Drive.hold_only``), ``auto`` (default) CST where 0x6502
announces it, else CSP with 0x60B2.
"""

from __future__ import annotations

from dataclasses import dataclass

from servobench.drivers.cia402_units import Overrides
from servobench.drivers.url import DriveURL
from servobench.errors import UsageError

QUERY_KEYS = frozenset(
    {"iface", "slave", "dc", "frame_timeout", "max_wkc_errors", "pos_scale", "vel_scale",
     "torque_constant", "mode"}
)  # fmt: skip
FRAME_TIMEOUT_S = 0.1
MAX_WKC_ERRORS = 10
DC_CHOICES = ("auto", "on", "off")
MODE_CHOICES = ("auto", "cst", "csp")


@dataclass(frozen=True)
class EthercatOptions:
    iface: str
    slave: int
    dc: str
    frame_timeout_s: float
    max_wkc_errors: int
    overrides: Overrides
    mode: str = "auto"

    @classmethod
    def from_url(cls, q: DriveURL) -> EthercatOptions:
        iface = q.get_str("iface") or q.host
        if not iface:
            raise UsageError("ethercat:// needs the network interface: ethercat://IFACE?slave=1")
        slave = q.get_int("slave", 1)
        if slave < 1:
            raise UsageError(f"slave={slave}: the first slave on the bus is 1")
        dc = q.get_str("dc", "auto")
        if dc not in DC_CHOICES:
            raise UsageError(f"dc={dc!r}: choose one of {', '.join(DC_CHOICES)}")
        timeout = q.get_float("frame_timeout", FRAME_TIMEOUT_S)
        if not timeout > 0:
            raise UsageError("frame_timeout must be > 0 s")
        mode = q.get_str("mode", "auto")
        if mode not in MODE_CHOICES:
            raise UsageError(f"mode={mode!r}: choose one of {', '.join(MODE_CHOICES)}")
        max_wkc = q.get_int("max_wkc_errors", MAX_WKC_ERRORS)
        if max_wkc < 1:
            raise UsageError("max_wkc_errors must be >= 1")
        return cls(
            iface, slave, dc, timeout, max_wkc,
            Overrides(q.get_float("pos_scale"), q.get_float("vel_scale"),
                      q.get_float("torque_constant")),
            mode,
        )  # fmt: skip

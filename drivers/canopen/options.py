"""The options of a ``canopen://`` URL, checked once (see :mod:`servobench.drivers.canopen.drive`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

from servobench.drivers.cia402 import MODE_CSP, MODE_CST, MODE_PROFILE_TORQUE
from servobench.drivers.cia402_units import Overrides
from servobench.drivers.url import DriveURL
from servobench.errors import DriveConfigError

#: Query keys of ``canopen://`` beyond the common ones.
QUERY_KEYS = frozenset(
    {"interface", "channel", "node", "bitrate", "host", "port", "mode", "host_node",
     "sdo_timeout", "pdo_timeout", "pos_scale", "vel_scale", "torque_constant", "eds",
     "sync_cob"}
)  # fmt: skip
#: SDO response timeout unless the URL sets ``sdo_timeout`` [s].  A drive
#: answers within milliseconds; the margin is for a loaded host or a
#: socketcand hop, and only a drive that never answers waits it out.
SDO_TIMEOUT_S = 1.0
#: Wait for the TPDOs of one SYNC unless the URL sets ``pdo_timeout`` [s].
PDO_TIMEOUT_S = 0.1
#: Command modes by URL name: (0x6060 value, description). ``csp``: the torque offset
#: 0x60B2 under the drive's own cyclic synchronous position hold (``Drive.hold_only``).
MODES = {
    "cst": (MODE_CST, "cyclic synchronous torque"),
    "pt": (MODE_PROFILE_TORQUE, "profile torque"),
    "csp": (MODE_CSP, "cyclic synchronous position"),
}
#: ``mode`` unset: CST where 0x6502 announces it, else CSP with the torque offset 0x60B2.
AUTO = "auto"
#: COB-ID of the SYNC the host produces (0x1005) unless the URL sets ``sync_cob``.
SYNC_COB_ID = 0x80
#: CiA 301 restricted 11-bit COB-IDs, which no SYNC may use (inclusive ranges).
RESTRICTED_COB_IDS = (
    (0x000, 0x07F), (0x101, 0x180), (0x581, 0x5FF), (0x601, 0x67F),
    (0x6E0, 0x6FF), (0x701, 0x77F), (0x780, 0x7FF),
)  # fmt: skip


@dataclass(frozen=True)
class CanopenOptions:
    """Everything a ``canopen://`` URL says besides the safety keys."""

    interface: str
    channel: str
    node_id: int
    host_node: int
    bitrate: int
    server: tuple[str, int] | None  # the socketcand server
    mode: int
    mode_name: str
    sdo_timeout_s: float
    pdo_timeout_s: float
    overrides: Overrides
    eds_path: str | None
    sync_cob: int
    #: The URL's ``mode``: a key of :data:`MODES`, or :data:`AUTO` (``mode`` unset).
    mode_key: str = "cst"

    @classmethod
    def from_url(cls, q: DriveURL) -> CanopenOptions:
        interface = q.get_str("interface", "socketcan")
        channel = q.get_str("channel") or q.host
        if not channel:
            raise DriveConfigError("canopen:// needs a channel: canopen://CHANNEL?... or channel=")
        node_id, host_node = q.get_int("node"), q.get_int("host_node", 127)
        if node_id is None or not 1 <= node_id <= 127:
            raise DriveConfigError("canopen:// needs node=1..127, the drive's node id")
        if not 1 <= host_node <= 127 or host_node == node_id:
            raise DriveConfigError(f"host_node must be 1..127 and not the drive's node {node_id}")
        mode_key = q.get_str("mode", AUTO)
        if mode_key not in (*MODES, AUTO):
            raise DriveConfigError(f"mode must be one of {', '.join(MODES)}, got {mode_key!r}")
        mode = "cst" if mode_key == AUTO else mode_key
        timeouts = (
            q.get_float("sdo_timeout", SDO_TIMEOUT_S),
            q.get_float("pdo_timeout", PDO_TIMEOUT_S),
        )
        overrides = Overrides(
            q.get_float("pos_scale"), q.get_float("vel_scale"), q.get_float("torque_constant")
        )
        scales = [
            s
            for s in (overrides.pos_scale, overrides.vel_scale, overrides.torque_constant)
            if s is not None
        ]
        if min((*timeouts, *scales)) <= 0:
            raise DriveConfigError(
                "sdo_timeout, pdo_timeout, pos_scale, vel_scale and torque_constant must be > 0"
            )
        bitrate = q.get_int("bitrate", 1_000_000)
        if bitrate <= 0:
            raise DriveConfigError(f"bitrate must be > 0 bit/s, got {bitrate}")
        return cls(
            interface=interface, channel=channel, node_id=node_id, host_node=host_node,
            bitrate=bitrate, server=_server(q, interface),
            mode=MODES[mode][0], mode_name=MODES[mode][1], sdo_timeout_s=timeouts[0],
            pdo_timeout_s=timeouts[1], overrides=overrides, eds_path=q.get_str("eds") or None,
            sync_cob=_sync_cob(q, node_id), mode_key=mode_key,
        )  # fmt: skip

    def with_mode(self, key: str) -> CanopenOptions:
        """These options commanding in mode ``key`` (of :data:`MODES`)."""
        return replace(self, mode=MODES[key][0], mode_name=MODES[key][1], mode_key=key)


def _server(q: DriveURL, interface: str) -> tuple[str, int] | None:
    if interface == "socketcand":
        if "host" not in q.query or "port" not in q.query:
            raise DriveConfigError(
                "interface=socketcand needs host= and port= of the socketcand server"
            )
        return q.get_str("host"), q.get_int("port")
    if "host" in q.query or "port" in q.query:
        raise DriveConfigError("host= and port= apply to interface=socketcand only")
    return None


def _sync_cob(q: DriveURL, node_id: int) -> int:
    cob = q.get_int("sync_cob", SYNC_COB_ID)
    if not 0 < cob <= 0x7FF or any(lo <= cob <= hi for lo, hi in RESTRICTED_COB_IDS):
        raise DriveConfigError(
            f"sync_cob=0x{cob:X} is not a usable 11-bit COB-ID "
            "(CiA 301 restricts 0x000-0x07F, 0x101-0x180, 0x581-0x5FF, 0x601-0x67F, 0x6E0-0x7FF)"
        )
    if cob in (0x80 + node_id, 0x180 + node_id, 0x280 + node_id, 0x200 + node_id, 0x300 + node_id):
        raise DriveConfigError(
            f"sync_cob=0x{cob:X} collides with node {node_id}'s own EMCY or PDOs"
        )
    return cob

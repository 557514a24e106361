"""SDO access for ``canopen://``: typed errors, and which objects the drive has.

:class:`SdoAccess` reads and writes objects of a :class:`canopen.RemoteNode`
and turns every failure into a :class:`~servobench.errors.DriveError`
(an SDO abort names its code, a silent node is a time-out, a broken link a
connection error). :class:`DriveObjects` answers "does the drive have this
object, and can it map it into a PDO?": from the drive's EDS when the URL
names one, else by SDO probing, where abort 0x06020000 ("object does not
exist", 0x06090011 for a sub-index) means no.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import can
import canopen
from canopen.objectdictionary import ODVariable

from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveError,
    DriveTimeoutError,
)

#: SDO aborts (CiA 301) meaning "this drive has no such object / sub-index".
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
ABSENT = (ABORT_NO_OBJECT, ABORT_NO_SUBINDEX)


def aborted_with(err: BaseException, codes: tuple[int, ...]) -> bool:
    """True when ``err`` was caused by an SDO abort with one of ``codes``."""
    cause = err if isinstance(err, canopen.SdoAbortedError) else err.__cause__
    return isinstance(cause, canopen.SdoAbortedError) and cause.code in codes


class SdoAccess:
    """Typed SDO reads and writes of one node (the types come from its object dictionary)."""

    def __init__(self, node: canopen.RemoteNode, timeout_s: float) -> None:
        self.node = node
        self.timeout_s = timeout_s
        node.sdo.RESPONSE_TIMEOUT = timeout_s

    @property
    def node_id(self) -> int:
        return self.node.id

    @contextmanager
    def translated(self, what: str, error: type[DriveError] = DriveConfigError) -> Iterator[None]:
        """Turn canopen and python-can failures during ``what`` into servobench errors."""
        try:
            yield
        except canopen.SdoAbortedError as err:
            raise error(
                f"node {self.node_id}: {what} refused, SDO abort 0x{err.code:08X} ({err})"
            ) from err
        except canopen.SdoCommunicationError as err:
            raise DriveTimeoutError(
                f"node {self.node_id} did not answer SDO ({what}) within {self.timeout_s} s: {err}"
            ) from err
        except (can.CanError, OSError) as err:
            raise DriveConnectionError(f"CAN link failed during {what}: {err}") from err

    def variable(self, index: int, sub: int = 0) -> ODVariable:
        var = self.node.sdo.get_variable(index, sub)
        if var is None:
            raise DriveConfigError(
                f"object 0x{index:04X}:{sub} is not in the object dictionary servobench "
                "uses for this drive (name the drive's EDS with eds=)"
            )
        return var

    def read(self, index: int, sub: int = 0):
        """The value of ``index:sub``, decoded by its type."""
        with self.translated(f"read 0x{index:04X}:{sub}"):
            return self.variable(index, sub).raw

    def write(
        self, index: int, sub: int, value, error: type[DriveError] = DriveConfigError
    ) -> None:
        """Write ``value`` to ``index:sub``; a refusal raises ``error``."""
        with self.translated(f"write 0x{index:04X}:{sub} = {value!r}", error):
            self.variable(index, sub).raw = value

    def exists(self, index: int, sub: int = 0) -> bool:
        """Probe by SDO upload: False on abort 0x06020000/0x06090011, True on an answer or
        any other abort (the object is there but refuses, e.g. write-only)."""
        try:
            with self.translated(f"probe 0x{index:04X}:{sub}"):
                self.node.sdo.upload(index, sub)
        except DriveConfigError as err:
            if aborted_with(err, ABSENT):
                return False
        return True


class DriveObjects:
    """Which objects the drive has and which it maps into PDOs.

    Parameters
    ----------
    od : canopen.ObjectDictionary
        The drive's EDS when ``from_eds``; else the shipped generic CiA 402
        EDS, which gives the standard types and mapping flags only.
    from_eds : bool
        True when ``od`` is the drive's own EDS: presence is read from it.
    sdo : SdoAccess, optional
        For probing, when ``from_eds`` is False.
    """

    def __init__(
        self, od: canopen.ObjectDictionary, from_eds: bool, sdo: SdoAccess | None = None
    ) -> None:
        if not from_eds and sdo is None:
            raise ValueError("probing needs an SdoAccess")
        self.od = od
        self.from_eds = from_eds
        self.sdo = sdo
        self.source = "EDS" if from_eds else "SDO probing"
        self._known: dict[tuple[int, int], bool] = {}
        self._unmappable: set[tuple[int, int]] = set()

    def _in_od(self, index: int, sub: int) -> ODVariable | None:
        if index not in self.od:
            return None
        obj = self.od[index]
        if isinstance(obj, ODVariable):
            return obj if sub == 0 else None
        if sub not in obj:  # not obj.get(): an ODArray makes up sub-indices it lacks
            return None
        return obj[sub]

    def has(self, index: int, sub: int = 0) -> bool:
        """True when the drive has object ``index:sub``."""
        key = (index, sub)
        if key not in self._known:
            if self.from_eds:
                self._known[key] = self._in_od(index, sub) is not None
            else:
                self._known[key] = self.sdo.exists(index, sub)
        return self._known[key]

    def mappable(self, index: int, sub: int = 0, *, receive: bool) -> bool:
        """True when the drive has ``index:sub`` and may map it into an RPDO (``receive``) or a TPDO."""
        var = self._in_od(index, sub)
        if var is None or (index, sub) in self._unmappable or not self.has(index, sub):
            return False
        return var.pdo_mappable and (var.writable if receive else var.readable)

    def refuse_mapping(self, index: int, sub: int = 0) -> None:
        """Note that the drive refused to map ``index:sub`` (probing could not tell)."""
        self._unmappable.add((index, sub))

    def value(self, index: int, sub: int = 0, default=None):
        """The object's value read by SDO, or ``default`` when the drive lacks it.

        Probing and reading are one SDO upload: an abort 0x06020000 / 0x06090011
        marks the object absent.
        """
        key = (index, sub)
        if self.from_eds or key in self._known:
            return self.sdo.read(index, sub) if self.has(index, sub) else default
        try:
            value = self.sdo.read(index, sub)
        except DriveConfigError as err:
            if not aborted_with(err, ABSENT):
                raise
            self._known[key] = False
            return default
        self._known[key] = True
        return value

    def pair(self, index: int) -> tuple[int, int] | None:
        """Sub-indices 1 and 2 of a ratio object (0x608F, 0x6091, 0x6092), ``None`` if absent."""
        first = self.value(index, 1)
        second = self.value(index, 2) if first is not None else None
        return None if second is None else (first, second)

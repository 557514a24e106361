"""The fault injector: between the served simulated drive and its transport.

Every served transport clocks its :class:`~servobench.sim_backend.device.SimulatedDevice`
through a :class:`FaultInjector` instead of calling it directly::

    wire = injector.next_cycle()   # a clocking request arrived: count it, apply drive faults
    ...                            # the transport hook may refuse the request (wire faults)
    sample = injector.step()       # clock the drive; frozen feedback applied

:meth:`FaultInjector.next_cycle` applies the faults of the drive itself
(``fault``, ``freeze``) and returns the wire faults due at this cycle, which
the transport's hook (:mod:`servobench.sim_backend.faults.can`, ``.modbus``, ``.serial``)
carries out, because only it knows what a lost, late or garbled answer is on
its wire. Every fault applied is recorded in :attr:`FaultInjector.injected`
for the state report (:mod:`servobench.sim_backend.faults.state`).

Frozen feedback freezes position and velocity only: the drive's clock, power
state and fault code run on (the sensor stopped, not the drive). The
device's own ``frozen_feedback`` hook, which freezes the whole sample, is
left to in-process tests.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace

from servobench.sim_backend.device import DeviceSample, SimulatedDevice
from servobench.sim_backend.faults.spec import FaultPlan, FaultSpec


@dataclass(frozen=True)
class Injected:
    """A fault that was applied: what, at which cycle."""

    spec: FaultSpec

    def as_dict(self) -> dict[str, object]:
        return {"kind": self.spec.kind, "cycle": self.spec.cycle, "arg": self.spec.arg}


class FaultInjector:
    """Counts the drive's cycles and applies a :class:`FaultPlan` to them.

    Parameters
    ----------
    device : SimulatedDevice
        The served drive.
    plan : FaultPlan
        What to inject; an empty plan makes the injector a pass-through.
    """

    def __init__(self, device: SimulatedDevice, plan: FaultPlan) -> None:
        self.device = device
        self.plan = plan
        self.cycle = 0
        self.injected: list[Injected] = []
        self._lock = threading.Lock()
        self._freeze_at: int | None = None
        self._frozen: tuple[float, float] | None = None

    @property
    def transport(self) -> str:
        return self.plan.transport

    def next_cycle(self) -> tuple[FaultSpec, ...]:
        """Count one clocking request; apply the drive faults due; return the wire faults due."""
        with self._lock:
            self.cycle += 1
            due = self.plan.at(self.cycle)
            self.injected.extend(Injected(s) for s in due)
        for spec in due:
            if spec.kind == "fault":
                self.device.fault(int(spec.arg or 0), f"injected by --fault {spec}")
            elif spec.kind == "freeze" and self._freeze_at is None:
                self._freeze_at = self.cycle
        return tuple(s for s in due if not s.device)

    def step(self) -> DeviceSample:
        """Clock the drive one cycle (``device.step()``) with frozen feedback applied."""
        sample = self.device.step()
        if self._frozen is None and self._freeze_at is not None and self.cycle >= self._freeze_at:
            self._frozen = (sample.velocity, sample.position)
            return sample
        return self._apply_freeze(sample)

    def sample(self) -> DeviceSample:
        """The present feedback without clocking (``device.sample()``), frozen if frozen."""
        return self._apply_freeze(self.device.sample())

    def _apply_freeze(self, sample: DeviceSample) -> DeviceSample:
        if self._frozen is None:
            return sample
        return replace(sample, velocity=self._frozen[0], position=self._frozen[1])

    def record(self) -> list[dict[str, object]]:
        """The faults applied so far, as JSON-ready dicts."""
        with self._lock:
            return [i.as_dict() for i in self.injected]

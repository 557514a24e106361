"""A plant integrated in continuous (wall-clock) time, under commands that arrive at instants.

:class:`TimedPlant` is the physics of a simulated drive that does not wait
for its host (``clock=real``, :mod:`servobench.sim_backend.device`): the
plant moves between any two instants the drive looks at it, under the
command in force, and a command takes force at the instant it arrives (or,
with a transport delay, that long after). The contract:

* :meth:`TimedPlant.advance_to` integrates the plant from the instant it was
  last integrated up to ``t`` [s, any clock], holding the acting command
  over each stretch between command changes (zero-order hold in continuous
  time). Stretches are integrated in sub-steps no longer than ``max_step_s``
  (the drive's configured cycle) unless the model is exact for any step
  (the base Coulomb plant and the piecewise-linear effects: one step per
  stretch, the zero-velocity crossing solved analytically inside it);
* :meth:`TimedPlant.latch` makes ``u`` the command from ``t + delay_s`` on;
  :meth:`TimedPlant.latch_at` does so from an instant still to come (a drive
  with a control tick: the next tick), a later command for the same instant
  replacing the earlier;
  :meth:`TimedPlant.cut` removes the torque at once (power stage off) and
  drops commands still in the delay line;
* the transport delay of the ``delay`` effect is taken out of the model
  (whose delay line counts intervals of a fixed step) and applied here in
  time, so it stays exact however irregular the arrivals are.

Measurements (noise, quantization) are the :class:`~servobench.sim_backend.physics.plant.Plant`'s,
taken when the drive samples (:meth:`TimedPlant.measure`).
"""

from __future__ import annotations

import math
from collections import deque

from servobench.sim_backend.physics.plant import Plant

#: Most sub-steps of one stretch; a longer idle stretch takes longer sub-steps.
MAX_SUBSTEPS = 100_000


class TimedPlant:
    """A :class:`Plant` integrated up to arbitrary instants (see the module doc).

    Parameters
    ----------
    plant : Plant
        The plant; its transport delay (if any) moves here.
    t_s : float
        Instant [s] the plant's present state belongs to.
    max_step_s : float
        Longest sub-step [s] for models that are not exact for any step.
    """

    def __init__(self, plant: Plant, t_s: float, max_step_s: float) -> None:
        self.plant = plant
        self.delay_s = plant.detach_delay()
        self.max_step_s = float(max_step_s)
        self.t_s = float(t_s)  # instant up to which the plant has been integrated
        self.acting = 0.0  # command acting on the plant now
        self._pending: deque[tuple[float, float]] = deque()  # (takes force at [s], command)

    def latch(self, t_s: float, u: float) -> None:
        """Command ``u`` takes force at ``t_s + delay_s`` (integrate up to ``t_s`` first)."""
        self.advance_to(t_s)
        if self.delay_s > 0:
            self._pending.append((t_s + self.delay_s, float(u)))
        else:
            self.acting = float(u)

    def latch_at(self, t_act_s: float, u: float) -> None:
        """Command ``u`` takes force at ``t_act_s + delay_s``, an instant still to come.

        For a drive with a control tick of its own: ``t_act_s`` is the tick the
        command acts from. A command pending for that instant or a later one
        (an earlier command that arrived in the same tick) is replaced: the
        later command wins, the earlier never acts.
        """
        t_s = float(t_act_s) + self.delay_s
        while self._pending and self._pending[-1][0] >= t_s:
            self._pending.pop()
        self._pending.append((t_s, float(u)))

    def cut(self, t_s: float) -> None:
        """Torque off at ``t_s``: no command acts any more, none is pending."""
        self.advance_to(t_s)
        self._pending.clear()
        self.acting = 0.0

    def advance_to(self, t_s: float) -> float:
        """Integrate up to ``t_s`` (earlier instants: nothing); return the span integrated [s]."""
        start = self.t_s
        while self._pending and self._pending[0][0] <= t_s:
            t_change, u = self._pending.popleft()
            self._hold(t_change)
            self.acting = u
        self._hold(t_s)
        return max(0.0, self.t_s - start)

    def _hold(self, t_s: float) -> None:
        span = t_s - self.t_s
        if span <= 0:
            return
        self.t_s = t_s
        plant = self.plant
        if self.acting == 0.0 and plant.at_rest():
            return  # nothing moves: a body at rest without command stays at rest
        n = 1 if plant.exact else min(MAX_SUBSTEPS, max(1, math.ceil(span / self.max_step_s - 1e-9)))
        plant.hold(self.acting, span, n)

    def measure(self) -> tuple[float, float]:
        """Measured ``(velocity, position)`` of the present state (noise, quantization)."""
        return self.plant.measure()

"""Closed-loop logs of hidden-effect plants: the SIDBE pair added to a host's hold loop.

As :func:`servobench.bench.run.closed.stream_closed_runs` streams it on a
limited-travel axis: the host's loop (:class:`~servobench.bench.run.hold.HoldLoop`)
holds the axis at ``x_ref = 0`` with the bandwidth the travel planner gives
it (a fifth of the lowest excited line, :data:`~servobench.bench.run.hold.LINE_OVER_BANDWIDTH`),
the command of cycle ``k`` uses the feedback of cycle ``k - 1`` (the noisy,
possibly quantised velocity reading and the position), each run starts from
rest at the held position with the integral reset, and the log carries ``u``
(total), ``u_exc``, ``x_ref`` and the loop's metadata (``loop = closed``). The
plant is the case's own, stepped one cycle at a time (:class:`ClosedPlant`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from servobench.bench.log.io import LogWriter
from servobench.bench.run.hold import LINE_OVER_BANDWIDTH, HoldController, HoldLoop, design_hold
from servobench.sim_backend.physics.plant import PlantState

#: Columns of the log (a closed-loop log's, without host times: the samples are exact).
COLUMNS = ("run", "t", "u", "v", "x", "u_exc", "x_ref")


@dataclass(frozen=True)
class ClosedPlant:
    """What a closed-loop case needs of its hidden-effect plant (given by
    :func:`servobench.bench.testing.hidden_effects.write_case_log`, so this module does not
    import it): the base plant's ``M`` and ``B``, the log's rate [Hz] and SIDBE period [s], the
    excitation's metadata, the plant model (``simulate(u, dt, state)``), its sensor noise
    ``noise(rng, n)`` and its velocity reading ``read(v)``."""

    M: float
    B: float
    fs_hz: float
    period_s: float
    metadata: dict
    model: object
    noise: Callable[[np.random.Generator, int], np.ndarray]
    read: Callable[[np.ndarray], np.ndarray]


def hold_controller(plant: ClosedPlant) -> HoldController:
    """The host's hold loop for ``plant``, designed on its base plant."""
    bandwidth_hz = 1.0 / plant.period_s / LINE_OVER_BANDWIDTH
    gains = design_hold(plant.M, plant.B, bandwidth_hz)
    return HoldController(gains, "host", 0.0, 1.0 / plant.fs_hz)


def closed_run(plant: ClosedPlant, u_exc: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """One closed-loop run from rest at the held position: ``(u, v, x)`` as logged (``v`` the
    reading, noise included)."""
    controller = hold_controller(plant)
    loop = HoldLoop(controller)
    dt = 1.0 / plant.fs_hz
    n = len(u_exc)
    noise = plant.noise(rng, n)
    state = PlantState(0.0, controller.x_ref)
    u, v, x = np.empty(n), np.empty(n), np.empty(n)
    seen_x, seen_v = state.x, 0.0
    one = np.empty(1)
    for k, uk in enumerate(np.asarray(u_exc, dtype=float).tolist()):
        x[k] = state.x
        v[k] = float(plant.read(np.array([state.v + noise[k]]))[0])
        one[0] = u[k] = loop.command(uk, seen_x, seen_v)  # the previous cycle's feedback
        seen_x, seen_v = x[k], v[k]
        _, _, state = plant.model.simulate(one, dt, state)
    return u, v, x


def write_closed_log(
    plant: ClosedPlant, path: str | Path, commands: Sequence[tuple[int, np.ndarray]], seed: int
) -> Path:
    """Write the closed-loop log of ``plant``'s SIDBE pair ``commands`` (the excitation)."""
    path = Path(path)
    controller = hold_controller(plant)
    metadata = {**plant.metadata, **controller.metadata()}
    with LogWriter(path, metadata, columns=COLUMNS) as writer:
        for number, u_exc in commands:
            u, v, x = closed_run(plant, u_exc, np.random.default_rng(seed + number))
            t = np.arange(u.size) / plant.fs_hz
            x_ref = np.full(u.size, controller.x_ref)
            writer.append_block(np.full(u.size, number), t, u, v, x, u_exc, x_ref)
    return path

"""The simulated servo: the plant's physics, its state, sensor noise and quantization.

The physics is the DC servo with Coulomb friction of
:mod:`servobench.sim_backend.physics.coulomb` (exact under zero-order hold), or,
when the parameters name effects, :class:`~servobench.sim_backend.physics.rich_plant.RichModel`.
:class:`PlantParams`, :class:`PlantState` and :func:`simulate_coulomb` are
defined in :mod:`~servobench.sim_backend.physics.coulomb` and importable from here.

Sampling: ``v[k]`` and ``x[k]`` are taken at ``t_k``, before ``u[k]`` acts on
``[t_k, t_k + dt)``.
"""

from __future__ import annotations

import numpy as np

from servobench.sim_backend.physics.coulomb import PlantParams, PlantState, simulate_coulomb

__all__ = ["Plant", "PlantParams", "PlantState", "simulate", "simulate_coulomb"]


class Plant:
    """A simulated servo with state, sensor noise and quantization.

    Parameters
    ----------
    params : PlantParams
        The physics.
    rng : numpy.random.Generator, optional
        Source of sensor noise; by default seeded from ``params.seed``.
    compiled : bool
        Integrate effects with the compiled kernels (:mod:`.kernels`); False keeps the
        reference loops, which give the same numbers: a drive's own loop must never stop for
        a just-in-time compile or a cache load.
    """

    def __init__(
        self, params: PlantParams, rng: np.random.Generator | None = None, compiled: bool = True
    ) -> None:
        self.params = params
        self.rng = rng if rng is not None else np.random.default_rng(params.seed)
        self.state = PlantState()
        self._model = _make_model(params, compiled)

    def reset(self, v: float = 0.0, x: float = 0.0) -> None:
        self.state = PlantState(v, x)
        reset = getattr(self._model, "reset", None)
        if reset is not None:
            reset()

    def step_block(self, u: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Advance ``len(u)`` intervals; return measured ``(v, x)`` at each interval start."""
        v, x, self.state = self._model.simulate(np.asarray(u, dtype=float), dt_s, self.state)
        return self._measure(v, x)

    # ------------------------------------------------ continuous time (clock=real)
    @property
    def exact(self) -> bool:
        """True when one integration step of any length is exact (no sub-steps needed)."""
        return bool(getattr(self._model, "exact", True))

    def at_rest(self) -> bool:
        """True when, without command, nothing can move: the base plant with its body at rest."""
        return isinstance(self._model, _CoulombModel) and self.state.v == 0.0

    def detach_delay(self) -> float:
        """Take the transport delay out of the model and return it [s] (0 without one).

        The model's delay line counts intervals of one fixed step; a plant
        integrated over irregular spans (:mod:`servobench.sim_backend.physics.realtime`)
        delays its commands in time instead.
        """
        terms = getattr(self._model, "terms", None)
        if terms is None or not terms.delay_s:
            return 0.0
        delay_s, terms.delay_s = float(terms.delay_s), 0.0
        self._model.forget_step()
        return delay_s

    def hold(self, u: float, span_s: float, substeps: int = 1) -> None:
        """Integrate ``span_s`` [s] with ``u`` held, in ``substeps`` equal steps (nothing measured)."""
        _, _, self.state = self._model.simulate(np.full(int(substeps), float(u)), span_s / substeps, self.state)

    def measure(self) -> tuple[float, float]:
        """Measured ``(velocity, position)`` of the present state."""
        v, x = self._measure(np.array([self.state.v]), np.array([self.state.x]))
        return float(v[0]), float(x[0])

    def _measure(self, v: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self.params
        if p.noise > 0:
            v = v + self.rng.normal(0.0, p.noise, v.shape)
        if p.noise_x > 0:
            x = x + self.rng.normal(0.0, p.noise_x, x.shape)
        if p.res_v > 0:
            v = np.round(v / p.res_v) * p.res_v
        if p.res_x > 0:
            x = np.round(x / p.res_x) * p.res_x
        return v, x


class _CoulombModel:
    """The base physics: linear block plus Coulomb/breakaway friction, exact ZOH."""

    def __init__(self, params: PlantParams) -> None:
        self.params = params

    def simulate(
        self, u: np.ndarray, dt_s: float, state: PlantState
    ) -> tuple[np.ndarray, np.ndarray, PlantState]:
        return simulate_coulomb(u, dt_s, self.params, state)


def _make_model(params: PlantParams, compiled: bool = True):
    if not params.effects:
        return _CoulombModel(params)
    # the effects' simulator (and with it numba) only where there are effects: a served base plant,
    # the commonest drive, starts without them
    from servobench.sim_backend.physics.effects import collect_terms
    from servobench.sim_backend.physics.rich_plant import RichModel, build_model

    return build_model(params) if compiled else RichModel(params, collect_terms(params), reference=True)


def simulate(
    u: np.ndarray, fs_hz: float, params: PlantParams, rng: np.random.Generator | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Measured velocity and position of a plant at rest, driven by ``u`` sampled at ``fs_hz``."""
    plant = Plant(params, rng)
    return plant.step_block(u, 1.0 / fs_hz)

"""What an effect module declares: parameters, simulation terms, screening.

Every effect module in :mod:`servobench.sim_backend.physics.effects` defines

* ``EFFECT`` -- an :class:`EffectSpec` (name, parameters with ``sim://`` keys
  and units, the detection signature and the fitting method in words);
* ``contribute(p, plant, terms)`` -- adds its model term to a :class:`Terms`
  collection that :mod:`servobench.sim_backend.physics.rich_plant` integrates;
* ``screen(ctx)`` -- looks for its signature in a :class:`ScreenInput` and
  returns a :class:`Screening` (score, parameter guess, bounds, evidence);
* optionally ``check(p, plant)`` -- cross-checks against the base plant;
* optionally ``project(p, base)`` -- keeps refitted parameters physical (the
  diagnosis applies it at every step of a refit);
* optionally ``order(p)`` -- the model order of a parameter set (a spline's
  knot count) when a screening's alternatives differ in it: the diagnosis
  then keeps a higher order only when it pays on held-out data.

Callers reach the optional three through the registry's ``check``, ``project``
and ``order`` (:mod:`servobench.sim_backend.physics.effects`), which supply the
defaults for a module that does not define them: nothing to check, parameters
unchanged, one model order.

All are pure functions of numbers and arrays: no I/O, no globals.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from servobench.errors import UsageError


@dataclass(frozen=True)
class ParamSpec:
    """One physical parameter of an effect.

    Attributes
    ----------
    name : str
        Parameter name inside the effect (``"vs"``).
    key : str
        ``sim://`` query key (``"stribeck_vs"``); unique across the library.
    unit : str
        Physical unit, e.g. ``"command units"``, ``"units/s"``, ``"s"``, ``"rad/s"``.
    doc : str
        One line of meaning.
    lower, upper : float
        Allowed range (inclusive unless ``open_lower``).
    open_lower : bool
        Whether ``lower`` itself is excluded (``> 0`` rather than ``>= 0``).
    default : float or None
        Value used when the key is absent; ``None`` makes the key required.
    """

    name: str
    key: str
    unit: str
    doc: str
    lower: float = -math.inf
    upper: float = math.inf
    open_lower: bool = False
    default: float | None = None

    def validate(self, value: float, effect: str) -> float:
        value = float(value)
        low_ok = value > self.lower if self.open_lower else value >= self.lower
        if not (math.isfinite(value) and low_ok and value <= self.upper):
            rng = f"{'(' if self.open_lower else '['}{self.lower:g}, {self.upper:g}]"
            raise UsageError(f"{effect} {self.key}={value!r} out of range {rng} [{self.unit}]")
        return value


@dataclass(frozen=True)
class EffectSpec:
    """Declaration of one effect of the library."""

    name: str
    summary: str
    params: tuple[ParamSpec, ...]
    signature: str
    fit: str

    def keys(self) -> dict[str, ParamSpec]:
        return {p.key: p for p in self.params}


@dataclass(frozen=True)
class Coupling:
    """A second body behind the motor: spring (resonance) or play (backlash).

    Attributes
    ----------
    kind : {"spring", "gap"}
    load_ratio : float
        Share of the inertia (and of the viscous term) on the load side, in (0, 1).
    stiffness, damping : float
        Spring [command units / position unit] and damper [command units * s / unit] (spring).
    gap : float
        Total play [position units] (gap).
    measured : {"motor", "load"}
        Which body the sensor sits on.
    """

    kind: str
    load_ratio: float
    stiffness: float = 0.0
    damping: float = 0.0
    gap: float = 0.0
    measured: str = "motor"


# ------------------------------------------------------------------ terms as data
# The velocity- and position-dependent terms are callables (the reference integrator calls
# them) that also carry their coefficients as data, which the compiled integrator
# (:mod:`servobench.sim_backend.physics.kernels`) reads: an effect contributes one of these,
# never a bare function, so that its plant runs compiled. A bare callable (a test's plant
# outside the library) is integrated by the reference loop.


@dataclass(frozen=True)
class GaussianExcess:
    """Friction excess ``(pos if direction > 0 else neg) * exp(-(speed * inv_speed)^2)``.

    ``pos``, ``neg`` [command units] are the excess at rest in each direction, ``inv_speed``
    [s/unit] the inverse of the speed at which it has fallen to ``1/e`` (Stribeck).
    """

    pos: float
    neg: float
    inv_speed: float

    def __call__(self, speed: float, direction: int) -> float:
        z = speed * self.inv_speed
        return (self.pos if direction > 0 else self.neg) * math.exp(-z * z)


@dataclass(frozen=True)
class TableFriction:
    """Friction [command units] interpolated linearly in ``values`` along the travel.

    ``values[i]`` holds at ``x0 + i / scale`` [units]; the end values hold beyond the ends.
    """

    x0: float
    scale: float
    values: tuple[float, ...]

    def __call__(self, x: float) -> float:
        values = self.values
        last = len(values) - 1
        s = (x - self.x0) * self.scale
        if s <= 0.0:
            return values[0]
        if s >= last:
            return values[last]
        i = int(s)
        w = s - i
        return values[i] + w * (values[i + 1] - values[i])


@dataclass(frozen=True)
class SineForce:
    """Force ``amp * sin(k * x + phase)`` [command units] opposing the command at position ``x``."""

    amp: float
    k: float
    phase: float

    def __call__(self, x: float) -> float:
        return self.amp * math.sin(self.k * x + self.phase)


@dataclass
class Terms:
    """Model terms collected from the active effects, read by the integrator.

    Attributes
    ----------
    inputs : list of (int, callable)
        Memoryless command transforms ``u -> u`` (vectorized), applied in ascending order.
    delay_s : float
        Transport delay of the command [s].
    dB : float
        Viscous asymmetry: ``B_pos = B + dB``, ``B_neg = B - dB``.
    friction_excess : callable(speed, direction) -> float, optional
        Friction magnitude added to the Coulomb level of that direction at ``|v| = speed``
        (a :class:`GaussianExcess` runs compiled).
    friction_at : callable(x) -> float, optional
        Friction magnitude added to both Coulomb levels and both breakaway levels at motor
        position ``x`` [command units]; held over each integration sub-step (a
        :class:`TableFriction` runs compiled).
    static_pos, static_neg : float
        Breakaway levels at rest (the larger of these and the plant's breakaway applies).
    position_forces : list of callable(x) -> float
        Forces opposing the command at motor position ``x`` [command units] (each a
        :class:`SineForce` runs compiled).
    coupling : Coupling, optional
    substep_s : float
        Longest integration sub-step the terms tolerate [s] (``inf``: exact, no sub-steps).
    """

    inputs: list[tuple[int, Callable[[np.ndarray], np.ndarray]]] = field(default_factory=list)
    delay_s: float = 0.0
    dB: float = 0.0
    friction_excess: Callable[[float, int], float] | None = None
    friction_at: Callable[[float], float] | None = None
    static_pos: float = 0.0
    static_neg: float = 0.0
    position_forces: list[Callable[[float], float]] = field(default_factory=list)
    coupling: Coupling | None = None
    substep_s: float = math.inf


# ------------------------------------------------------------------ screening
@dataclass(frozen=True)
class RunSignals:
    """One run as screening sees it; arrays of shape ``(n,)``.

    ``v_f``, ``a_f``, ``u_f`` are zero-phase low-passed velocity [units/s],
    acceleration [units/s^2] and ZOH-centred command [command units];
    ``residual`` is measured minus base-simulated velocity [units/s].
    """

    u: np.ndarray
    v: np.ndarray
    x: np.ndarray
    v_f: np.ndarray
    a_f: np.ndarray
    u_f: np.ndarray
    residual: np.ndarray
    v_sim: np.ndarray


@dataclass(frozen=True)
class ScreenInput:
    """Everything a screening function may use.

    Attributes
    ----------
    runs : tuple of RunSignals
    dt_s : float
        Sample interval [s].
    base : Mapping[str, float]
        Base model ``M, B, coulomb_pos, coulomb_neg``.
    effects : Mapping[str, Mapping[str, float]]
        Effects already in the model (their terms are in ``residual`` already).
    moving : ndarray of bool
        Samples (all runs concatenated) where the inverse-dynamics equation holds.
    command_filter : callable
        What made ``u_f`` from one run's command: ZOH centring and the zero-phase low-pass.
    held_out : ndarray of bool
        Samples (all runs concatenated) kept out of every fit, for choices made on held-out
        data (all False when the caller holds nothing out).
    """

    runs: tuple[RunSignals, ...]
    dt_s: float
    base: Mapping[str, float]
    effects: Mapping[str, Mapping[str, float]]
    moving: np.ndarray
    command_filter: Callable[[np.ndarray], np.ndarray]
    held_out: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.held_out is None:
            object.__setattr__(self, "held_out", np.zeros(self.moving.size, dtype=bool))

    def cat(self, name: str) -> np.ndarray:
        """Signal ``name`` of all runs, concatenated."""
        return np.concatenate([getattr(r, name) for r in self.runs])

    @cached_property
    def base_qr(self) -> tuple[np.ndarray, np.ndarray]:
        """QR factors of the base regressors on the moving samples (reused for every target)."""
        return np.linalg.qr(np.column_stack(base_columns(self)))


@dataclass(frozen=True)
class Screening:
    """What a screening function found.

    Attributes
    ----------
    score : float
        Fraction of the base equation error (or residual) the term explains, in [0, 1].
    guess : Mapping[str, float]
        Starting parameters.
    bounds : Mapping[str, tuple[float, float]]
        Search range of each fitted parameter.
    evidence : str
        One sentence naming the signature found.
    fixed : tuple of str
        Parameters held at ``guess`` during the gradient refit (piecewise-constant ones).
    base : Mapping[str, float], optional
        Base parameters (``M, B, coulomb_pos, coulomb_neg``) fitted jointly with the term, if any.
    scan : tuple of str
        Parameters on which the error is rugged (a play that closes or not before a
        reversal, a period): scanned coarsely before the gradient refit.
    alternatives : tuple of mappings
        Further starting guesses, judged by a quick simulation like ``guess``.
    restarts : tuple of (base, guess) pairs
        Further starts that move the base as well (``M, B, coulomb_pos, coulomb_neg`` with
        the term's parameters): where the current base has absorbed the term (a Coulomb level
        fitted at the breakaway of an axis that mostly sticks), no guess on that base reaches
        the term's basin. Judged by the quick simulation with the alternatives.
    """

    score: float
    guess: Mapping[str, float]
    bounds: Mapping[str, tuple[float, float]]
    evidence: str
    fixed: tuple[str, ...] = ()
    base: Mapping[str, float] | None = None
    scan: tuple[str, ...] = ()
    alternatives: tuple[Mapping[str, float], ...] = ()
    restarts: tuple[tuple[Mapping[str, float], Mapping[str, float]], ...] = ()


def regress(columns: list[np.ndarray], target: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares ``target ~ columns``; return coefficients and residual sum of squares."""
    A = np.column_stack(columns)
    coef, *_ = np.linalg.lstsq(A, target, rcond=None)
    resid = target - A @ coef
    return coef, float(resid @ resid)


def base_values(ctx: ScreenInput) -> dict[str, float]:
    """The current base model's ``M, B, coulomb_pos, coulomb_neg`` as floats (a restart's
    starting point)."""
    return {k: float(ctx.base[k]) for k in ("M", "B", "coulomb_pos", "coulomb_neg")}


def base_columns(ctx: ScreenInput) -> list[np.ndarray]:
    """Inverse-dynamics regressors of the base model on the moving samples: a, v, [v>0], -[v<0]."""
    m = ctx.moving
    a, v = ctx.cat("a_f")[m], ctx.cat("v_f")[m]
    return [a, v, (v > 0).astype(float), -(v < 0).astype(float)]


def target(ctx: ScreenInput) -> np.ndarray:
    return ctx.cat("u_f")[ctx.moving]


def explained(sse_base: float, sse_new: float, extra_params: int, n: int) -> float:
    """Fraction of the base error removed, less a BIC-like allowance for ``extra_params``."""
    if sse_base <= 0 or n <= 0:
        return 0.0
    allowance = extra_params * math.log(max(n, 2)) / max(n, 2)
    return max(0.0, 1.0 - sse_new / sse_base - allowance)


def base_fit(ctx: ScreenInput) -> tuple[np.ndarray, float]:
    """Equation-error fit of the base model on the moving samples."""
    return regress(base_columns(ctx), target(ctx))


def input_fit(
    ctx: ScreenInput, transform: Callable[[np.ndarray], np.ndarray]
) -> tuple[np.ndarray, float]:
    """Equation-error fit of the base model to a transformed command ``transform(u)``."""
    y = np.concatenate([ctx.command_filter(transform(r.u)) for r in ctx.runs])[ctx.moving]
    q, r = ctx.base_qr
    qty = q.T @ y
    coef = np.linalg.lstsq(r, qty, rcond=None)[0]  # R is singular when one direction never moves
    return coef, max(float(y @ y - qty @ qty), 0.0)

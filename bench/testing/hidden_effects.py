"""Hidden-effect plants and their logs, for tests and benchmarks of the diagnosis.

:func:`random_case` draws a base plant and one or more library effects with
random parameters from ranges where the effect is identifiable from a two-run
log (documented per effect below), at a chosen ``strength`` (1 = those
ranges, 0.5 = every effect halfway to the base plant). :func:`write_case_log`
excites it, adds velocity-sensor noise (white, or low-passed: coloured) and
writes a servobench log. Only the log goes to the diagnosis. All randomness
comes from an explicit ``numpy.random.Generator``.

Inputs (``inputs=``):

* ``two-level`` (default): a binary-plus-multisine command at two amplitudes,
  run 1 and run 2 (like SIDBE's u1/u2, amplitude ratio 2);
* ``sidbe``: the SIDBE pair itself -- a periodic multi-frequency binary
  excitation ``u1`` and ``u2 = 0.9 u1`` (:mod:`servobench.bench.procedure.excitation`),
  with its design in the log's metadata;
* ``square``, ``sine``, ``triangle``: one run of the classic test commands,
  period :data:`WAVE_PERIOD_S`;
* ``single``: one run of the ``two-level`` command (its first amplitude);
* ``closed``: the SIDBE pair added to a host's hold loop that keeps the axis in a
  travel window, as ``sidbe`` streams it on a limited-travel axis
  (:mod:`servobench.bench.testing.closed_case`).

Velocity-sensor noise: white, coloured (low-passed white) or quantised (the
reading rounded to a step, ``noise_step``). :mod:`servobench.bench.testing.sized_cases`
draws each effect at a size in units of the Coulomb level (or of its own natural scale).

Plants outside the library (``outside=``) add a term no effect module
models: ``spring`` (a force pulling the axis towards the middle of its
travel) or ``drag`` (friction growing with the square of the speed).
:func:`issue_case` is issue 12's plant: Coulomb friction growing along the
travel, sensor noise about 1 % of the velocity.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from servobench.bench.log.io import ExperimentLog, LogWriter
from servobench.sim_backend.physics.effects import collect_terms, position_friction
from servobench.sim_backend.physics.plant import Plant, PlantParams, PlantState
from servobench.sim_backend.physics.rich_plant import RichModel
from servobench.sim_backend.simurl import plant_query

#: Sample rate of the generated logs [Hz] and duration of each run [s].
CASE_FS_HZ = 500.0
CASE_RUN_S = 2.0
#: Run 2 amplitude over run 1 amplitude.
AMPLITUDE_RATIO = 2.0
#: Velocity-sensor noise as a fraction of the steady speed at run-2 amplitude.
NOISE_FRACTION = 0.002
#: The command shapes a case can be excited with.
INPUTS = ("two-level", "sidbe", "square", "sine", "triangle", "single", "closed")
#: Period of the square, sine and triangle commands [s] and the length of their one run [s].
WAVE_PERIOD_S = 1.0
WAVE_RUN_S = 4.0
#: Peak of the square, sine and triangle commands, in units of the case amplitude.
WAVE_PEAK = 1.5
#: SIDBE pair: period [s], periods per run (the first is the transient), u2/u1.
SIDBE_PERIOD_S = 1.0
SIDBE_PERIODS = 3
SIDBE_RATIO = 0.9
#: Terms outside the library a case can add.
OUTSIDE = ("spring", "drag")


@dataclass(frozen=True)
class HiddenCase:
    """A plant with hidden effects and how it is excited.

    Attributes
    ----------
    effect : str or None
        The first hidden library effect (None: none).
    params : PlantParams
        The plant, effects included (``noise`` is the white-noise level even when the
        log's noise is coloured).
    amplitude : float
        Command amplitude of run 1 [command units].
    effects : dict
        The hidden library effects and their parameters, in the order drawn.
    inputs : str
        One of :data:`INPUTS`.
    noise_colour_hz : float
        Corner [Hz] of the first-order low-pass that colours the sensor noise (0: white).
    outside : dict
        Terms outside the library (``{"spring": k}`` [command units/unit],
        ``{"drag": c}`` [command units s^2/unit^2]) and ``centre`` [units] of the spring.
    commands : tuple of (run, ndarray)
        Commands drawn with the plant (position friction needs them to place its knots);
        empty: :func:`case_commands` draws them.
    noise_step : float
        Step [units/s] the velocity reading is rounded to (0: not quantised).
    """

    effect: str | None
    params: PlantParams
    amplitude: float
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    inputs: str = "two-level"
    noise_colour_hz: float = 0.0
    outside: dict[str, float] = field(default_factory=dict)
    commands: tuple[tuple[int, np.ndarray], ...] = ()
    noise_step: float = 0.0

    @property
    def names(self) -> tuple[str, ...]:
        """Every hidden library effect."""
        return tuple(self.effects)

    def sim_url(self) -> str:
        """The ``sim://`` URL of this plant (white noise included; outside terms cannot be)."""
        keys = plant_query(self.params)
        return "sim://?" + "&".join(f"{k}={v:.10g}" for k, v in keys.items())


def excitation(rng: np.random.Generator, n: int, fs_hz: float, amplitude: float) -> np.ndarray:
    """Binary command with random hold times plus a multisine: many levels, rich spectrum.

    ``u = amplitude * (0.65 b + 0.35 m)``: ``b = +/-1`` held 20-150 ms, ``m`` a
    random-phase multisine of 0.5-20 Hz scaled to a peak of 1.
    """
    levels = []
    while sum(len(x) for x in levels) < n:
        hold = int(rng.uniform(0.02, 0.15) * fs_hz) + 1
        levels.append(np.full(hold, rng.choice([-1.0, 1.0])))
    binary = np.concatenate(levels)[:n]
    t = np.arange(n) / fs_hz
    freqs = np.geomspace(0.5, 20.0, 12)
    m = sum(np.sin(2 * math.pi * f * t + rng.uniform(0, 2 * math.pi)) for f in freqs)
    m = m / np.max(np.abs(m))
    return amplitude * (0.65 * binary + 0.35 * m)


def wave(shape: str, n: int, fs_hz: float, peak: float, period_s: float = WAVE_PERIOD_S):
    """Square, sine or triangle command of ``peak`` [command units] and ``period_s`` [s]."""
    phase = (np.arange(n) / fs_hz / period_s) % 1.0
    if shape == "square":
        return peak * np.where(phase < 0.5, 1.0, -1.0)
    if shape == "sine":
        return peak * np.sin(2 * math.pi * phase)
    if shape == "triangle":
        return peak * (1.0 - 4.0 * np.abs(((phase + 0.25) % 1.0) - 0.5))
    raise ValueError(f"unknown wave {shape!r} (square, sine, triangle)")


def _toward(base: float, full: float, strength: float) -> float:
    """A parameter ``strength`` of the way from ``base`` (no effect) to ``full``."""
    return full if strength == 1.0 else base + strength * (full - base)


def _effect_params(
    effect: str, base: PlantParams, amp: float, rng: np.random.Generator, strength: float = 1.0
) -> dict:
    u = rng.uniform
    s = strength
    fc = 0.5 * (base.coulomb_pos + base.coulomb_neg)
    v_typ = amp / base.B
    sign = rng.choice([-1.0, 1.0])
    if effect == "stribeck":
        top = max(base.coulomb_pos, base.coulomb_neg)
        return {"fs": _toward(top, top * u(1.8, 2.6), s), "vs": v_typ * u(0.05, 0.15)}
    if effect == "viscous_asymmetry":
        return {"dB": s * sign * base.B * u(0.3, 0.5)}
    if effect == "offset":
        # Below the Coulomb level an offset is exactly a Coulomb asymmetry: only larger ones show.
        level = base.coulomb_pos if sign > 0 else base.coulomb_neg
        return {"offset": s * sign * level * u(1.5, 2.2)}
    if effect == "time_delay":
        return {"delay": s * u(3.0, 8.0) / CASE_FS_HZ}
    if effect == "resonance":
        return {"wn": 2 * math.pi * u(12.0, 35.0), "zeta": u(0.03, 0.1), "ratio": 0.5 * s}
    if effect == "cogging":
        return {"amp": s * fc * u(0.6, 1.2), "period": u(0.08, 0.2), "phase": u(-math.pi, math.pi)}
    if effect == "saturation":
        top = AMPLITUDE_RATIO * amp
        return {"limit": _toward(top, top * u(0.5, 0.7), s)}
    if effect == "backlash":
        return {"gap": s * u(0.03, 0.08), "ratio": u(0.35, 0.6)}
    if effect == "deadzone":
        return {"width": s * amp * u(0.3, 0.5)}
    if effect == "quantization":
        return {"step": s * amp * u(0.25, 0.45)}
    if effect == "position_friction":
        # A smooth rise (or fall) along the travel with a bump: knots placed later on the travel.
        n = int(rng.integers(4, 7))
        rise = sign * fc * u(0.8, 1.4)
        bump = fc * u(-0.4, 0.4) * np.sin(math.pi * np.linspace(0, 1, n))
        values = s * (rise * np.linspace(0.0, 1.0, n) + bump)
        values = np.maximum(values - values[0], -0.8 * min(base.coulomb_pos, base.coulomb_neg))
        values[0] = 0.0
        return position_friction_params(0.0, 1.0, values)
    raise ValueError(f"no parameter ranges for effect {effect!r}")


def position_friction_params(x_from: float, x_to: float, values: Sequence[float]) -> dict:
    """``position_friction`` parameters with knot ``values`` [command units] from ``x_from`` to
    ``x_to`` [units]."""
    out = {"x_from": float(x_from), "x_to": float(x_to), "knots": float(len(values))}
    for i in range(position_friction.MAX_KNOTS):
        out[f"f{i}"] = float(values[i]) if i < len(values) else 0.0
    return out


def random_case(
    effect: str | None | Sequence[str],
    rng: np.random.Generator,
    *,
    strength: float = 1.0,
    inputs: str = "two-level",
    noise_fraction: float = NOISE_FRACTION,
    noise_colour_hz: float = 0.0,
    outside: Mapping[str, float] | None = None,
) -> HiddenCase:
    """A random base plant with ``effect`` hidden in it (``None``: nothing; a sequence: several).

    ``outside`` names terms outside the library (:data:`OUTSIDE`) with their strength in
    units of the Coulomb level at the typical speed or travel (1: about as large as it).
    """
    if inputs not in INPUTS:
        raise ValueError(f"unknown inputs {inputs!r} (one of {', '.join(INPUTS)})")
    names = [] if effect is None else [effect] if isinstance(effect, str) else list(effect)
    M, B = rng.uniform(0.06, 0.15), rng.uniform(0.6, 1.5)
    fcp, fcn = rng.uniform(0.2, 0.5), rng.uniform(0.2, 0.5)
    amp = rng.uniform(4.0, 6.0) * max(fcp, fcn)
    noise = noise_fraction * AMPLITUDE_RATIO * amp / B
    base = PlantParams(M=M, B=B, coulomb_pos=fcp, coulomb_neg=fcn, noise=noise)
    effects = {n: _effect_params(n, base, amp, rng, strength) for n in names}
    case = HiddenCase(
        names[0] if names else None,
        base.with_changes(effects=effects),
        amp,
        effects,
        inputs,
        noise_colour_hz,
        {k: float(v) for k, v in (outside or {}).items()},
    )
    if "position_friction" in effects or case.outside:
        case = _placed(case, rng)
    return case


def _placed(case: HiddenCase, rng: np.random.Generator) -> HiddenCase:
    """Draw the commands now and place the travel-dependent terms on the travel they produce."""
    commands = tuple(case_commands(case, rng))
    plain = {k: v for k, v in case.effects.items() if k != "position_friction"}
    trial = replace(case, params=case.params.with_changes(effects=plain), outside={})
    xs = np.concatenate([_true_motion(trial, u)[1] for _, u in commands])
    lo, hi = position_friction.travel(xs)
    effects = dict(case.effects)
    if "position_friction" in effects:
        p = effects["position_friction"]
        effects["position_friction"] = {**p, "x_from": lo, "x_to": hi}
    fc = 0.5 * (case.params.coulomb_pos + case.params.coulomb_neg)
    outside = dict(case.outside)
    if "spring" in outside:  # force fc * strength at either end of the travel
        outside = {**outside, "spring": outside["spring"] * fc / (0.5 * (hi - lo) or 1.0)}
        outside["centre"] = 0.5 * (lo + hi)
    if "drag" in outside:  # force fc * strength at the typical speed
        v_typ = case.amplitude / case.params.B
        outside["drag"] = outside["drag"] * fc / v_typ**2
    return replace(
        case,
        params=case.params.with_changes(effects=effects),
        effects=effects,
        outside=outside,
        commands=commands,
    )


def issue_case(rng: np.random.Generator, inputs: str = "two-level") -> HiddenCase:
    """Issue 12's plant: M 0.1, B 1, Coulomb 0.5 / 0.4 growing smoothly along the travel (a worn
    screw section: +0.6 at the far end), velocity-sensor noise about 1 % of the velocity."""
    base = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
    rise = 0.6 * (1.0 - np.cos(math.pi * np.linspace(0.0, 1.0, 5))) / 2.0
    effects = {"position_friction": position_friction_params(0.0, 1.0, rise)}
    case = HiddenCase("position_friction", base.with_changes(effects=effects), 2.0, effects, inputs)
    case = _placed(case, rng)
    v = np.concatenate([_true_motion(case, u)[0] for _, u in case.commands])
    noise = 0.01 * float(np.std(v))
    return replace(case, params=case.params.with_changes(noise=noise))


def case_commands(case: HiddenCase, rng: np.random.Generator) -> list[tuple[int, np.ndarray]]:
    """The runs' commands: drawn with the case, or drawn now for its inputs."""
    if case.commands:
        return [(number, u.copy()) for number, u in case.commands]
    if case.inputs == "two-level":
        n = int(CASE_RUN_S * CASE_FS_HZ)
        return [
            (1, excitation(rng, n, CASE_FS_HZ, case.amplitude)),
            (2, excitation(rng, n, CASE_FS_HZ, AMPLITUDE_RATIO * case.amplitude)),
        ]
    if case.inputs in ("sidbe", "closed"):
        exc = _sidbe(case)
        return exc.runs()
    if case.inputs == "single":
        n = int(CASE_RUN_S * CASE_FS_HZ)
        return [(1, excitation(rng, n, CASE_FS_HZ, case.amplitude))]
    n = int(WAVE_RUN_S * CASE_FS_HZ)
    return [(1, wave(case.inputs, n, CASE_FS_HZ, WAVE_PEAK * case.amplitude))]


def _sidbe(case: HiddenCase):
    from servobench.bench.procedure.excitation import design_excitation, make_design

    design = make_design(
        WAVE_PEAK * case.amplitude,
        ratio=SIDBE_RATIO,
        fs_hz=CASE_FS_HZ,
        periods=SIDBE_PERIODS,
        period_s=SIDBE_PERIOD_S,
    )
    return design_excitation(design)


def log_metadata(case: HiddenCase) -> dict[str, object]:
    """Header of the case's log: the rate, and the SIDBE design for SIDBE pairs."""
    if case.inputs == "sidbe":
        return {**_sidbe(case).design.metadata(), "loop": "open"}
    return {"fs": CASE_FS_HZ}


def _true_motion(case: HiddenCase, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free ``(v, x)`` of one run from rest, outside terms included."""
    model = rich_model(case)
    v, x, _ = model.simulate(np.asarray(u, dtype=float), 1.0 / CASE_FS_HZ, PlantState())
    return v, x


def rich_model(case: HiddenCase) -> RichModel:
    """The case's plant as the simulator runs it, outside terms included."""
    terms = collect_terms(case.params)
    out = case.outside
    if "spring" in out:
        k, centre = out["spring"], out.get("centre", 0.0)
        terms.position_forces.append(lambda x: k * (x - centre))
    if "drag" in out:
        c = out["drag"]
        previous = terms.friction_excess
        terms.friction_excess = (
            (lambda speed, d: c * speed * speed)
            if previous is None
            else (lambda speed, d: previous(speed, d) + c * speed * speed)
        )
    return RichModel(case.params, terms)


def sensor_noise(case: HiddenCase, rng: np.random.Generator, n: int) -> np.ndarray:
    """The velocity sensor's noise of one run: white, or coloured (quantisation is applied to
    the reading, :func:`read_velocity`)."""
    if case.noise_colour_hz:
        return coloured(rng, n, case.params.noise, case.noise_colour_hz)
    return rng.normal(0.0, case.params.noise, n)


def read_velocity(case: HiddenCase, v: np.ndarray) -> np.ndarray:
    """The logged reading of velocity ``v`` (noise included): rounded to ``noise_step``."""
    step = case.noise_step
    return step * np.round(v / step) if step else v


def coloured(rng: np.random.Generator, n: int, std: float, corner_hz: float) -> np.ndarray:
    """Noise of standard deviation ``std``: white through a first-order low-pass at ``corner_hz``."""
    from scipy.signal import lfilter

    a = math.exp(-2 * math.pi * corner_hz / CASE_FS_HZ)
    w = lfilter([1.0 - a], [1.0, -a], rng.normal(0.0, 1.0, n + 2000))[2000:]
    return std * w / np.std(w)


def write_case_log(
    case: HiddenCase, path: str | Path, rng: np.random.Generator, noise_seed: int | None = None
) -> Path:
    """Simulate the runs (each from rest) and write ``run,t,u,v,x``; the effects are not named.

    ``noise_seed`` seeds the sensor's noise in place of the one drawn from ``rng`` (drawn all
    the same): the same excitation read through another realisation of the noise."""
    path = Path(path)
    seed = int(rng.integers(2**31))
    seed = seed if noise_seed is None else int(noise_seed)
    if case.inputs == "closed":
        from servobench.bench.testing.closed_case import ClosedPlant, write_closed_log

        plant = ClosedPlant(
            case.params.M, case.params.B, CASE_FS_HZ, SIDBE_PERIOD_S, _sidbe(case).design.metadata(),
            rich_model(case), lambda g, n: sensor_noise(case, g, n), lambda v: read_velocity(case, v),
        )  # fmt: skip
        return write_closed_log(plant, path, case_commands(case, rng), seed)
    plain = not case.outside and not case.noise_colour_hz and not case.noise_step
    with LogWriter(path, log_metadata(case)) as writer:
        for number, u in case_commands(case, rng):
            noise_rng = np.random.default_rng(seed + number)
            if plain:
                plant = Plant(case.params, noise_rng)
                v, x = plant.step_block(u, 1.0 / CASE_FS_HZ)
            else:
                v, x = _true_motion(case, u)
                v = read_velocity(case, v + sensor_noise(case, noise_rng, v.size))
            t = np.arange(u.size) / CASE_FS_HZ
            writer.append_block(np.full(u.size, number), t, u, v, x)
    return path


def true_floor(log: ExperimentLog, case: HiddenCase) -> float:
    """The gap [%] the case's hidden model itself leaves on its ``log`` (its noise, simulated back
    with the plant's own parameters by the diagnosis's simulator): the true noise floor a
    diagnosis's stated one is judged against."""
    from servobench.bench.diagnose.data import prepare
    from servobench.bench.diagnose.refit import evaluate
    from servobench.bench.diagnose.simulate import Candidate

    p = case.params
    base = {"M": p.M, "B": p.B, "coulomb_pos": p.coulomb_pos, "coulomb_neg": p.coulomb_neg}
    return evaluate(prepare(log), Candidate(base, {k: dict(v) for k, v in case.effects.items()})).gap


class CaseResults(dict):
    """Results of named cases, each computed in this process the first time it is asked for.

    What the diagnosis tests share across a module (a module-scoped fixture):
    one log and one diagnosis per case, made by the test worker itself (never
    a process pool nested in a worker) and only for the cases the selected
    tests read.
    """

    def __init__(self, run: Callable[[Hashable], dict]) -> None:
        super().__init__()
        self._run = run

    def __missing__(self, name: Hashable) -> dict:
        result = self[name] = self._run(name)
        return result

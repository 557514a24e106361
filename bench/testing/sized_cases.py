"""Hidden-effect plants at a size: the generator of issue 30's naming benchmark.

:func:`sized_case` draws a random base plant (as
:func:`~servobench.bench.testing.hidden_effects.random_case` does) with one library
effect at ``size`` times the Coulomb level, or times the effect's own natural
scale where its size is not a force (:func:`sized_params`), excited by any of
the :data:`~servobench.bench.testing.hidden_effects.INPUTS` and read through a
white, coloured or quantised velocity sensor. The log is written by
:func:`~servobench.bench.testing.hidden_effects.write_case_log`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from servobench.bench.testing.hidden_effects import (
    AMPLITUDE_RATIO,
    CASE_FS_HZ,
    NOISE_FRACTION,
    WAVE_PEAK,
    HiddenCase,
    _effect_params,
    _placed,
    position_friction_params,
    random_case,
)
from servobench.sim_backend.physics.plant import PlantParams

#: Velocity-sensor noises a case can have.
NOISES = ("white", "coloured", "quantised")

#: Natural scales of the effects whose size is not a force: a viscous asymmetry in viscous
#: coefficients, a delay in sample periods, a resonant load in shares of the inertia,
#: a saturation in shares of the peak command it cuts, a backlash gap [units].
DB_SCALE = 0.25
DELAY_SAMPLES = 3.0
RATIO_SCALE = 0.2
LIMIT_SCALE = 0.25
GAP_SCALE = 0.025


def sized_params(
    effect: str, base: PlantParams, amp: float, rng: np.random.Generator, size: float
) -> dict:
    """Parameters of ``effect`` at ``size`` (0.5-3) times the Coulomb level ``fc`` (mean of
    the two), or times its own natural scale (:data:`DB_SCALE` ...): a Stribeck excess
    ``size * fc`` over the higher Coulomb level, an offset, a cogging amplitude, a dead band,
    a command step, a friction rise along the travel of ``size * fc``; a viscous asymmetry
    of ``size * DB_SCALE * B``, a delay of ``size * DELAY_SAMPLES`` samples, a load of
    ``size * RATIO_SCALE`` of the inertia, a limit at ``1 / (1 + size * LIMIT_SCALE)`` of
    the peak command, a gap of ``size * GAP_SCALE``. The shapes (Stribeck velocity,
    cogging period, resonant frequency, ...) are drawn as :func:`random_case` draws them."""
    u = rng.uniform
    k = float(size)
    fc = 0.5 * (base.coulomb_pos + base.coulomb_neg)
    sign = float(rng.choice([-1.0, 1.0]))
    shape = _effect_params(effect, base, amp, rng)
    if effect == "stribeck":
        return {**shape, "fs": max(base.coulomb_pos, base.coulomb_neg) + k * fc}
    if effect == "viscous_asymmetry":
        return {"dB": sign * min(k * DB_SCALE, 0.8) * base.B}
    if effect == "offset":
        return {"offset": sign * k * fc}
    if effect == "time_delay":
        return {"delay": k * DELAY_SAMPLES / CASE_FS_HZ}
    if effect == "resonance":
        return {**shape, "ratio": min(k * RATIO_SCALE, 0.8)}
    if effect == "cogging":
        return {**shape, "amp": k * fc}
    if effect == "saturation":
        return {"limit": WAVE_PEAK * AMPLITUDE_RATIO * amp / (1.0 + k * LIMIT_SCALE)}
    if effect == "backlash":
        return {**shape, "gap": k * GAP_SCALE * u(0.8, 1.2)}
    if effect == "deadzone":
        return {"width": k * fc}
    if effect == "quantization":
        return {"step": k * fc}
    if effect == "position_friction":
        n = int(shape["knots"])
        values = np.array([shape[f"f{i}"] for i in range(n)])
        top = float(np.max(np.abs(values))) or 1.0
        values = np.maximum(values * k * fc / top, -0.8 * min(base.coulomb_pos, base.coulomb_neg))
        values[0] = 0.0
        return position_friction_params(0.0, 1.0, values)
    raise ValueError(f"no sizes for effect {effect!r}")


def sized_case(
    effect: str | None,
    rng: np.random.Generator,
    size: float,
    *,
    inputs: str = "two-level",
    noise: str = "white",
    noise_fraction: float = NOISE_FRACTION,
) -> HiddenCase:
    """A random base plant with ``effect`` (None: nothing) at ``size`` (:func:`sized_params`),
    excited by ``inputs`` and read through a sensor whose noise is ``white``, ``coloured``
    (low-passed at 5-25 Hz) or ``quantised`` (white noise, the reading rounded to about three
    of its standard deviations)."""
    if noise not in NOISES:
        raise ValueError(f"unknown noise {noise!r} (one of {', '.join(NOISES)})")
    plain = random_case(None, rng, inputs=inputs, noise_fraction=noise_fraction)
    base, amp = plain.params, plain.amplitude
    effects = {} if effect is None else {effect: sized_params(effect, base, amp, rng, size)}
    colour = float(rng.uniform(5.0, 25.0)) if noise == "coloured" else 0.0
    step = float(rng.uniform(2.5, 3.5)) * base.noise if noise == "quantised" else 0.0
    case = replace(
        plain,
        effect=effect,
        params=base.with_changes(effects=effects),
        effects=effects,
        noise_colour_hz=colour,
        noise_step=step,
    )
    return _placed(case, rng) if "position_friction" in effects else case

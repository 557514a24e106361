"""Hidden-effect plants and their logs, for tests and benchmarks of the diagnosis.

:func:`random_case` draws a base plant and one library effect with random
parameters from ranges where the effect is identifiable from a two-run log
(documented per effect below); :func:`write_case_log` excites it with a
binary-plus-multisine command at two amplitudes (run 1 and run 2, like
SIDBE's u1/u2), adds velocity-sensor noise and writes a servobench log. Only
the log goes to the diagnosis. All randomness comes from an explicit
``numpy.random.Generator``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from servobench.bench.logio import LogWriter
from servobench.sim_backend.physics.plant import Plant, PlantParams
from servobench.sim_backend.simurl import plant_query

#: Sample rate of the generated logs [Hz] and duration of each run [s].
CASE_FS_HZ = 500.0
CASE_RUN_S = 2.0
#: Run 2 amplitude over run 1 amplitude.
AMPLITUDE_RATIO = 2.0
#: Velocity-sensor noise as a fraction of the steady speed at run-2 amplitude.
NOISE_FRACTION = 0.002


@dataclass(frozen=True)
class HiddenCase:
    """A plant with (at most) one hidden effect and the command amplitude of run 1."""

    effect: str | None
    params: PlantParams
    amplitude: float
    effects: dict[str, dict[str, float]] = field(default_factory=dict)

    def sim_url(self) -> str:
        """The ``sim://`` URL of this plant (noise included)."""
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


def _effect_params(effect: str, base: PlantParams, amp: float, rng: np.random.Generator) -> dict:
    u = rng.uniform
    fc = 0.5 * (base.coulomb_pos + base.coulomb_neg)
    v_typ = amp / base.B
    sign = rng.choice([-1.0, 1.0])
    if effect == "stribeck":
        return {
            "fs": max(base.coulomb_pos, base.coulomb_neg) * u(1.8, 2.6),
            "vs": v_typ * u(0.05, 0.15),
        }
    if effect == "viscous_asymmetry":
        return {"dB": sign * base.B * u(0.3, 0.5)}
    if effect == "offset":
        # Below the Coulomb level an offset is exactly a Coulomb asymmetry: only larger ones show.
        level = base.coulomb_pos if sign > 0 else base.coulomb_neg
        return {"offset": sign * level * u(1.5, 2.2)}
    if effect == "time_delay":
        return {"delay": u(3.0, 8.0) / CASE_FS_HZ}
    if effect == "resonance":
        return {"wn": 2 * math.pi * u(12.0, 35.0), "zeta": u(0.03, 0.1), "ratio": 0.5}
    if effect == "cogging":
        return {"amp": fc * u(0.6, 1.2), "period": u(0.08, 0.2), "phase": u(-math.pi, math.pi)}
    if effect == "saturation":
        return {"limit": AMPLITUDE_RATIO * amp * u(0.5, 0.7)}
    if effect == "backlash":
        return {"gap": u(0.03, 0.08), "ratio": u(0.35, 0.6)}
    if effect == "deadzone":
        return {"width": amp * u(0.3, 0.5)}
    if effect == "quantization":
        return {"step": amp * u(0.25, 0.45)}
    raise ValueError(f"no parameter ranges for effect {effect!r}")


def random_case(effect: str | None, rng: np.random.Generator) -> HiddenCase:
    """A random base plant with ``effect`` hidden in it (``None``: nothing hidden)."""
    M, B = rng.uniform(0.06, 0.15), rng.uniform(0.6, 1.5)
    fcp, fcn = rng.uniform(0.2, 0.5), rng.uniform(0.2, 0.5)
    amp = rng.uniform(4.0, 6.0) * max(fcp, fcn)
    noise = NOISE_FRACTION * AMPLITUDE_RATIO * amp / B
    base = PlantParams(M=M, B=B, coulomb_pos=fcp, coulomb_neg=fcn, noise=noise)
    effects = {} if effect is None else {effect: _effect_params(effect, base, amp, rng)}
    return HiddenCase(effect, base.with_changes(effects=effects), amp, effects)


def case_commands(case: HiddenCase, rng: np.random.Generator) -> list[tuple[int, np.ndarray]]:
    """Run 1 and run 2 commands (run 2 at :data:`AMPLITUDE_RATIO` times the amplitude)."""
    n = int(CASE_RUN_S * CASE_FS_HZ)
    return [
        (1, excitation(rng, n, CASE_FS_HZ, case.amplitude)),
        (2, excitation(rng, n, CASE_FS_HZ, AMPLITUDE_RATIO * case.amplitude)),
    ]


def write_case_log(case: HiddenCase, path: str | Path, rng: np.random.Generator) -> Path:
    """Simulate both runs (each from rest) and write ``run,t,u,v,x``; the effect is not named."""
    path = Path(path)
    seed = int(rng.integers(2**31))
    with LogWriter(path, {"fs": CASE_FS_HZ}) as writer:
        for number, u in case_commands(case, rng):
            plant = Plant(case.params, np.random.default_rng(seed + number))
            v, x = plant.step_block(u, 1.0 / CASE_FS_HZ)
            t = np.arange(u.size) / CASE_FS_HZ
            writer.append_block(np.full(u.size, number), t, u, v, x)
    return path

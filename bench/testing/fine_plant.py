"""A Stribeck plant simulated independently of the library, finely, with a zero-order-hold command.

``M dv/dt + B v = u - F(v)``, ``F(v) = sign(v) (Fc_dir + Fs exp(-(v/vs)^2))``: a
Stribeck breakaway ``Fs`` added to each direction's Coulomb level ``Fc_dir``,
decaying with the Stribeck velocity ``vs``. At rest the axis sticks while the
command stays within the breakaway level ``Fc_dir + Fs`` of the direction it
pushes. The command is held over each sample period and the motion integrated
in :data:`SUBSTEPS` steps per sample (semi-implicit Euler, a reversal within a
step stops the axis at rest). Sample ``k`` is the state at its instant ``k / fs``, before
the command ``u[k]`` it carries acts (as the drive's own samples are).

This is how a new user's logs of issue 30 were made, and it shares no code with
the simulator the diagnosis fits (:mod:`servobench.sim_backend.physics`): the
diagnosis is judged against a plant it does not contain by construction. In the
library's terms the plant is ``stribeck`` with a static level per direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Integration steps per sample period.
SUBSTEPS = 50


@dataclass(frozen=True)
class StribeckPlant:
    """``M`` [command units s^2/unit], ``B`` [command units s/unit], Coulomb levels ``fc_pos``,
    ``fc_neg`` and breakaway excess ``fs`` [command units], Stribeck velocity ``vs`` [units/s]."""

    M: float
    B: float
    fc_pos: float
    fc_neg: float
    fs: float
    vs: float

    def simulate(
        self, u: np.ndarray, fs_hz: float, substeps: int = SUBSTEPS
    ) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free velocity [units/s] and position [units] at each sample instant, from
        rest, of the command ``u`` [command units] held from its instant to the next."""
        M, B, fs, inv_vs = self.M, self.B, self.fs, 1.0 / self.vs
        breakaway_pos, breakaway_neg = self.fc_pos + fs, self.fc_neg + fs
        dt = 1.0 / (fs_hz * substeps)
        v = x = 0.0
        vs_out = np.empty(len(u))
        xs_out = np.empty(len(u))
        exp = math.exp
        for i, ui in enumerate(np.asarray(u, dtype=float)):
            vs_out[i] = v
            xs_out[i] = x
            for _ in range(substeps):
                if v == 0.0:
                    if ui > breakaway_pos:
                        v = (ui - breakaway_pos) * dt / M
                    elif ui < -breakaway_neg:
                        v = (ui + breakaway_neg) * dt / M
                    x += 0.5 * v * dt
                    continue
                if v > 0.0:
                    friction = self.fc_pos + fs * exp(-((v * inv_vs) ** 2))
                else:
                    friction = -(self.fc_neg + fs * exp(-((v * inv_vs) ** 2)))
                # Viscous term implicit (stable at any B dt / M), friction explicit.
                new = (v + dt * (ui - friction) / M) / (1.0 + dt * B / M)
                if new * v < 0.0:
                    new = 0.0  # reversal within the step: the axis stops, sticks or breaks away
                x += 0.5 * (v + new) * dt
                v = new
        return vs_out, xs_out


def write_fine_log(
    plant: StribeckPlant,
    runs: list[tuple[int, np.ndarray]],
    path,
    rng: np.random.Generator,
    noise: float,
    metadata: dict[str, object],
    fs_hz: float,
):
    """Simulate each run from rest, add white velocity noise of std ``noise`` [units/s] and
    write ``run,t,u,v,x`` to ``path``; returns the path."""
    from pathlib import Path

    from servobench.bench.log.io import LogWriter

    path = Path(path)
    with LogWriter(path, metadata) as writer:
        for number, u in runs:
            v, x = plant.simulate(u, fs_hz)
            v = v + rng.normal(0.0, noise, v.size)
            t = np.arange(u.size) / fs_hz
            writer.append_block(np.full(u.size, number), t, u, v, x)
    return path


#: Issue 30's plants: a square-wave single run, and a SIDBE pair with a strong breakaway.
ISSUE_PLANTS = {
    "square": StribeckPlant(M=0.1708, B=1.4079, fc_pos=0.4061, fc_neg=0.2843, fs=1.015, vs=0.15),
    "sidbe": StribeckPlant(M=0.1855, B=0.6677, fc_pos=0.4691, fc_neg=0.3590, fs=1.1727, vs=0.1491),
}
#: Their logs' sample rate [Hz] and white velocity noise [units/s].
ISSUE_FS_HZ = 1000.0
ISSUE_NOISE = 0.005


def issue_runs(kind: str) -> tuple[list[tuple[int, np.ndarray]], dict[str, object]]:
    """Issue 30's runs and log header: ``square``, 8 s of a 1 Hz square wave of amplitude 2;
    ``sidbe``, a binary multisine on lines 1, 2, 3, 5 and 7 Hz, amplitude 2, 6 s each,
    ``u2 = 0.9 u1``."""
    from servobench.bench.procedure.excitation import design_excitation, make_design
    from servobench.bench.testing.hidden_effects import wave

    fs = ISSUE_FS_HZ
    if kind == "square":
        return [(1, wave("square", int(8 * fs), fs, 2.0, 1.0))], {"fs": fs}
    if kind == "sidbe":
        design = make_design(
            2.0, ratio=0.9, fs_hz=fs, periods=6, period_s=1.0, freqs_hz=(1, 2, 3, 5, 7)
        )
        exc = design_excitation(design)
        return exc.runs(), {**exc.design.metadata(), "loop": "open"}
    raise ValueError(f"unknown issue case {kind!r} (square, sidbe)")


def write_issue_log(kind: str, path, rng: np.random.Generator):
    """Issue 30's log ``kind`` (``square``, ``sidbe``) at ``path``, noise drawn from ``rng``."""
    runs, metadata = issue_runs(kind)
    return write_fine_log(ISSUE_PLANTS[kind], runs, path, rng, ISSUE_NOISE, metadata, ISSUE_FS_HZ)

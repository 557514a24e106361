"""Step 6: does the final model explain the data? The noise floor, the verdict, where the residual lives.

Noise floor [% of the measured velocity's standard deviation, like the gap]:
:mod:`.floor` -- the measurement's parts (sensor noise, the resolution of
every signal, the velocity estimate of a derived velocity), and the held-out
residual's unpredictable part, which raises the floor only when the residual
is noise-like (all places together predict less than
:data:`~servobench.bench.diagnose.floor.STRUCTURED` of it on held-out samples).
The verdict is ``explained`` when the final gap is within
:data:`VERDICT_FACTOR` of the floor, ``unexplained`` otherwise.

Where the residual lives: each *place* is a set of force-like regressors built
from the log and the final model's own simulated motion -- velocity
(piecewise-linear in the simulated velocity), position
(piecewise-linear in position, alone and signed by the direction of motion),
direction of motion, acceleration, time (since the last reversal, and along
the run), frequency (the command's recent history: a linear dynamic the
model lacks) and the command's level. Velocity, acceleration and direction come
from the simulated velocity, not the measured one: regressors built on the
measurement carry its noise, and would predict coloured noise as if it were
structure. A force error reaches the velocity
through the model's linear block ``1/(M s + B)``, so every regressor is
passed through it (restarted with each comparison window). Each place is fitted
to the residual on the training samples alone; its *share* is the part of the
held-out residual energy it predicts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from servobench.bench.diagnose.data import DiagnosisData
from servobench.bench.diagnose.floor import COLOURED, NoiseFloor, noise_floor
from servobench.bench.diagnose.simulate import Candidate

#: ``explained`` when the final gap is at most this multiple of the noise floor ...
VERDICT_FACTOR = 1.5
#: ... or below this absolute gap [%] (noise-free data simulated back exactly).
EXACT_GAP_PERCENT = 0.01
#: Knots of the piecewise-linear regressors per place, coarse and fine: each place's share is
#: the better of the two (a short log supports few knots, a long one more).
KNOTS = (
    {"velocity": 4, "position": 4, "acceleration": 4, "command": 4, "time": 3},
    {"velocity": 8, "position": 10, "acceleration": 6, "command": 6, "time": 6},
)
#: Times after a reversal [s] of the knots of the "time since reversal" regressors.
REVERSAL_KNOTS_S = (0.0, 0.01, 0.025, 0.05, 0.1, 0.2)
#: Lags [samples] of the command-history regressors.
LAGS = (0, 1, 2, 3, 4, 5, 6, 8, 10, 12, 15, 20, 30, 45)
#: Ridge weight of the place fits (relative to the training samples).
RIDGE = 1e-4
#: A place predicting this share of the held-out residual energy is where it lives.
STRONG = 0.25
#: Time constants [s, samples] the linear block of the place regressors is held within.
TAU_MAX_S = 1.0
TAU_MIN_SAMPLES = 2
#: Velocity below this fraction of its rms counts as at rest for the direction of motion.
REST_FRACTION = 0.02

PLACES = ("velocity", "position", "direction", "acceleration", "time", "frequency", "command")
LABELS = {
    "velocity": "velocity",
    "position": "position (signed by the direction of motion)",
    "direction": "the direction of motion",
    "acceleration": "acceleration",
    "time": "time (after reversals, along the run)",
    "frequency": "the frequency content of the command (its recent history: a linear dynamic "
    "the model lacks)",
    "command": "the command's level",
}


@dataclass(frozen=True)
class Place:
    """A place the residual may live: its held-out share of the residual energy, in [0, 1]."""

    name: str
    share: float


@dataclass(frozen=True)
class Verdict:
    """Result of :func:`judge`.

    Attributes
    ----------
    verdict : {"explained", "unexplained"}
    gap_percent : float
        The final model's gap [%].
    floor : NoiseFloor
    places : tuple of Place
        Strongest first.
    spectrum : str
        Where the residual's energy lies in frequency, in words.
    signature : str
        One sentence: the remaining gap against the floor and where the residual lives
        ("" when explained).
    """

    verdict: str
    gap_percent: float
    floor: NoiseFloor
    places: tuple[Place, ...]
    spectrum: str
    signature: str

    @property
    def explained(self) -> bool:
        return self.verdict == "explained"

    @property
    def ratio(self) -> float:
        """Gap over floor."""
        return self.gap_percent / self.floor.percent if self.floor.percent > 0 else math.inf

    def headline(self) -> str:
        """The line output leads with."""
        if self.explained:
            return (
                f"verdict: explained -- the model reproduces the measured velocity to within the "
                f"noise floor (gap {self.gap_percent:.3g}% against a floor of "
                f"{self.floor.percent:.3g}%)"
            )
        return f"verdict: unexplained -- {self.signature}"


# ------------------------------------------------------------------ regressors
def nodes_of(s: np.ndarray, knots: int) -> np.ndarray:
    """``knots`` nodes at the quantiles of ``s`` (duplicates merged)."""
    return np.unique(np.quantile(s, np.linspace(0.0, 1.0, knots)))


def hats(s: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Piecewise-linear (hat) basis over ``s`` with the given nodes, shape ``(n, nodes.size)``
    (a constant column when there are fewer than two)."""
    if nodes.size < 2:
        return np.ones((s.size, 1))
    eye = np.eye(nodes.size)
    return np.column_stack([np.interp(s, nodes, eye[i]) for i in range(nodes.size)])


def _since_reversal(d: np.ndarray, dt_s: float) -> np.ndarray:
    """Time [s] since the direction of motion last changed (or since the start)."""
    idx = np.arange(d.size)
    flips = np.concatenate([[True], d[1:] != d[:-1]])
    last = np.maximum.accumulate(np.where(flips, idx, 0))
    return (idx - last) * dt_s


def _signals(data: DiagnosisData, i: int, v_model: np.ndarray) -> dict[str, np.ndarray]:
    """The signals of run ``i`` the piecewise-linear places are built on; ``v_model`` is the
    model's simulated velocity of the run (noise-free)."""
    r = data.segments[i]
    return {
        "velocity": v_model,
        "position": r.position,
        "acceleration": np.gradient(v_model, data.dt_s),
        "command": r.u,
        "time": np.arange(len(r)) / len(r),
    }


def _run_places(
    data: DiagnosisData, i: int, nodes: Mapping[str, np.ndarray], v_model: np.ndarray
) -> dict[str, np.ndarray]:
    """The raw (unfiltered) regressors of run ``i``, per place; ``nodes`` of the piecewise-linear
    ones are shared by all runs (the columns mean the same in every run)."""
    sig = _signals(data, i, v_model)
    v, u = sig["velocity"], data.segments[i].u
    rms = float(np.sqrt(np.mean(v * v))) or 1.0
    d = np.where(np.abs(v) > REST_FRACTION * rms, np.sign(v), 0.0)
    since = _since_reversal(d, data.dt_s)
    rev = np.column_stack(
        [np.interp(since, REVERSAL_KNOTS_S, row) for row in np.eye(len(REVERSAL_KNOTS_S))]
    )
    lagged = np.column_stack([np.concatenate([np.zeros(k), u[: u.size - k]]) for k in LAGS])
    hx = hats(sig["position"], nodes["position"])
    return {
        "velocity": hats(sig["velocity"], nodes["velocity"]),
        "position": np.column_stack([hx * d[:, None], hx]),
        "direction": d[:, None],
        "acceleration": hats(sig["acceleration"], nodes["acceleration"]),
        "time": np.column_stack([rev * d[:, None], hats(sig["time"], nodes["time"])]),
        "frequency": lagged,
        "command": hats(sig["command"], nodes["command"]),
    }


def _through_block(phi: np.ndarray, starts: np.ndarray, M: float, B: float, dt: float):
    """``phi`` (columns of forces) through ``1/(M s + B)`` under ZOH, restarted at ``starts``;
    the time constant ``M/B`` held within [:data:`TAU_MIN_SAMPLES` dt, :data:`TAU_MAX_S`] (a
    fit with B near zero would integrate the regressors into drifts)."""
    from servobench.bench.dsp.iir import lfilter

    B = min(max(B, M / TAU_MAX_S), M / (TAU_MIN_SAMPLES * dt))
    a = math.exp(-dt * B / M)
    b = (1.0 - a) / B
    out = np.empty_like(phi)
    ends = np.append(starts[1:], phi.shape[0])
    for s, e in zip(starts, ends, strict=True):
        out[s:e] = lfilter([0.0, b], [1.0, -a], phi[s:e], axis=0)
    return out


def regressors(
    data: DiagnosisData,
    base: Mapping[str, float],
    knots: Mapping[str, int],
    v_model: Sequence[np.ndarray],
) -> dict[str, np.ndarray]:
    """Every place's regressors over all runs (concatenated), through the model's linear block;
    ``v_model`` is the model's simulated velocity per run."""
    M, B = float(base["M"]), float(base["B"])
    v_model = [_finite(v, r.v_f) for v, r in zip(v_model, data.segments, strict=True)]
    signals = [_signals(data, i, v) for i, v in enumerate(v_model)]
    nodes = {k: nodes_of(np.concatenate([s[k] for s in signals]), n) for k, n in knots.items()}
    per_run = []
    for i, starts in enumerate(data.starts):
        raw = _run_places(data, i, nodes, v_model[i])
        per_run.append({k: _through_block(v, starts, M, B, data.dt_s) for k, v in raw.items()})
    return {k: np.concatenate([p[k] for p in per_run]) for k in PLACES}


def _finite(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """``v`` with samples the simulation could not give taken from ``fallback``."""
    v = np.asarray(v, dtype=float)
    return np.where(np.isfinite(v), v, fallback)


def _held_out_share(X: np.ndarray, e: np.ndarray, train: np.ndarray, test: np.ndarray) -> float:
    """Share of the test samples' energy of ``e`` that a ridge fit of ``X`` on ``train`` predicts."""
    X = np.column_stack([X, np.ones(e.size)])  # a constant belongs to every place
    scale = np.sqrt(np.mean(X[train] ** 2, axis=0))
    scale[scale == 0] = 1.0
    Xs = X / scale
    A = Xs[train]
    lam = RIDGE * train.sum()
    coef = np.linalg.solve(A.T @ A + lam * np.eye(A.shape[1]), A.T @ e[train])
    miss = e[test] - Xs[test] @ coef
    energy = float(e[test] @ e[test])
    return max(0.0, 1.0 - float(miss @ miss) / energy) if energy > 0 else 0.0


# ------------------------------------------------------------------ floor and verdict
def _spectrum(data: DiagnosisData, e: np.ndarray) -> str:
    """Where the residual's energy lies in frequency, in words."""
    from servobench.bench.dsp.spectral import welch

    nper = int(min(max(64, 2 ** int(math.log2(max(e.size // 8, 64)))), e.size))
    f, p = welch(e, data.fs_hz, nper)
    if p.sum() <= 0:
        return "no residual energy"
    cum = np.cumsum(p) / p.sum()
    half = float(f[int(np.searchsorted(cum, 0.5))])
    peak = float(f[1 + int(np.argmax(p[1:]))]) if p.size > 1 else 0.0
    return f"half of its energy lies below {half:.3g} Hz, its spectrum peaks at {peak:.3g} Hz"


def _where(places: Sequence[Place]) -> str:
    strong = [p for p in places if p.share >= STRONG]
    others = ", ".join(f"{p.name} {100 * p.share:.0f}%" for p in places[1:4])
    if not strong:
        return (
            "no signal in the log predicts it on held-out samples (strongest: "
            f"{places[0].name} {100 * places[0].share:.0f}%): noise the floor does not count, "
            "or a disturbance independent of the motion"
        )
    top = strong[0]
    return (
        f"it lives against {LABELS[top.name]}, which predicts {100 * top.share:.0f}% of it on "
        f"held-out samples (then {others})"
    )


def shares(
    data: DiagnosisData,
    final: Candidate,
    v_sim: Sequence[np.ndarray],
    e: np.ndarray,
    train: np.ndarray,
    test: np.ndarray,
) -> tuple[dict[str, float], float]:
    """Held-out share of the residual ``e`` each place predicts, and all places together;
    ``v_sim`` is the final model's simulated velocity per run."""
    best = {k: 0.0 for k in PLACES}
    together = 0.0
    for knots in KNOTS:
        X = regressors(data, final.base, knots, v_sim)
        for k in PLACES:
            best[k] = max(best[k], _held_out_share(X[k], e, train, test))
        every = np.column_stack([X[k] for k in PLACES])
        together = max(together, _held_out_share(every, e, train, test))
    return best, max(together, *best.values())


def judge(
    data: DiagnosisData, final: Candidate, v_sim: Sequence[np.ndarray], gap: float
) -> Verdict:
    """The verdict on the final model ``final`` with simulated velocity ``v_sim`` and gap [%]."""
    e = np.concatenate([r.v - vs for r, vs in zip(data.segments, v_sim, strict=True)])
    ok = np.isfinite(e)
    held = np.concatenate(data.held_out)
    e = np.where(ok, e, 0.0)
    by_place, together = shares(data, final, v_sim, e, ok & ~held, ok & held)
    places = tuple(sorted((Place(k, s) for k, s in by_place.items()), key=lambda p: -p.share))
    floor = noise_floor(data, gap, together, v_sim, final.base)
    spectrum = _spectrum(data, e[ok])
    explained = gap <= EXACT_GAP_PERCENT or gap <= VERDICT_FACTOR * floor.percent
    signature = ""
    if not explained:
        f, up = floor.percent, floor.upper_percent
        ratio = f"{gap / f:.3g} times" if f > 0 else "far above"
        upto = (f" (coloured noise could reach {up:.3g}%: {gap / up:.3g} times that)"
                if up > COLOURED * f else "")  # fmt: skip
        signature = (
            f"the final model leaves a velocity gap of {gap:.3g}%, {ratio} the noise floor of "
            f"{f:.3g}%{upto}; {_where(places)}; {spectrum}"
        )
    verdict = "explained" if explained else "unexplained"
    return Verdict(verdict, gap, floor, places, spectrum, signature)

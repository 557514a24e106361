"""1-sigma of a diagnosed model's parameters, as the identification states them.

At the solution of a refit (:mod:`.refit`) the Jacobian of the training
residual with respect to the optimiser's parameters (``log M``, ``log B``, the
Coulomb levels and effect parameters scaled to order one) is taken to the
natural parameters by the chain rule and given to the noise-model sandwich of
:func:`servobench.bench.identify.covariance.noise_model_covariance`: the
sensor noise's autocovariance from an autoregression fitted to the residual,
each simulation window's noise independent of the others', on the windows'
every sample (held-out ones out of the cost, their lags kept), and the noise of
the measured velocity each window starts from carried with its gain. The
windows are short (a few hundred samples of a closed-loop log), where a lag
window (the HAC sandwich) states too small a sigma for noise correlated over
tens of samples: on Stribeck cases of ``diagnose_cases.py`` under coloured
sensor noise the rms of error over sigma was 1.2-1.5 with it.

The residual's whiteness
(:func:`~servobench.bench.identify.covariance.residual_colour`) goes with it:
a coloured residual is noted, its sigmas allow for it.

Parameters are named as ``model.json`` and the JSON name them: the base keys
``M``, ``B``, ``coulomb_pos``, ``coulomb_neg``, and ``"effect.parameter"``.
Parameters held fixed in the fit (grid-searched steps, parameters without
bounds) have no sigma. :meth:`ParameterCovariance.propagate` carries the
covariance to quantities computed from the parameters (the pole, a Stribeck
curve's static level net of a companion force, directional viscous
coefficients) to first order.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from servobench.bench.diagnose.simulate import Candidate
from servobench.bench.identify.covariance import (
    ResidualColour,
    noise_model_covariance,
    residual_colour,
)

#: Columns of the Jacobian smaller than this share of the largest are not determined by the data.
NULL_COLUMN = 1e-12
#: Step of the first-order propagation, in units of each parameter's sigma.
PROPAGATION_STEP = 1e-3
#: Fewest residual samples for the whiteness test.
MIN_SAMPLES = 8
#: Parameters that cannot be negative (fitted on a log scale).
POSITIVE = ("M", "B")
#: How the sigmas allow for a coloured residual, as its note says.
NOISE_MODEL = "a model of the noise (an autoregression fitted to the residual)"


@dataclass(frozen=True)
class ParameterCovariance:
    """Covariance of the fitted natural parameters.

    Attributes
    ----------
    names : tuple of str
        The fitted parameters (``M``, ``B``, ``coulomb_pos``, ``coulomb_neg``,
        ``"effect.parameter"``).
    values : tuple of float
        Their values at the solution.
    matrix : ndarray, shape (p, p)
        Covariance (:func:`natural_covariance`); NaN rows and columns for parameters the data do
        not determine.
    colour : ResidualColour or None
        Whiteness of the training residual.
    ranges : mapping
        ``{"effect.parameter": (low, high)}``: the bounds the effect parameters were fitted in.
    """

    names: tuple[str, ...]
    values: tuple[float, ...]
    matrix: np.ndarray
    colour: ResidualColour | None = None
    ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        p = len(self.names)
        if len(self.values) != p or np.shape(self.matrix) != (p, p):
            raise ValueError(
                f"a covariance of {p} parameters needs {p} values and a {p}x{p} matrix"
            )

    @property
    def std(self) -> dict[str, float]:
        """1-sigma of each fitted parameter (NaN where the data do not determine it)."""
        sd = np.sqrt(np.clip(np.diag(self.matrix), 0.0, None))
        return {n: float(s) for n, s in zip(self.names, sd, strict=True)}

    def propagate(
        self, f: Callable[[Mapping[str, float]], Mapping[str, float]]
    ) -> dict[str, float]:
        """1-sigma of each output of ``f`` (a function of the parameters by name) to first
        order, by central differences: NaN for an output that moves with a parameter the data
        do not determine; outputs that no fitted parameter moves are left out."""
        x0 = dict(zip(self.names, self.values, strict=True))
        sd = np.sqrt(np.clip(np.diag(self.matrix), 0.0, None))
        at = f(x0)
        outputs = list(at)
        G = np.zeros((len(outputs), len(self.names)))
        for j, (name, s) in enumerate(zip(self.names, sd, strict=True)):
            h = (
                PROPAGATION_STEP * s
                if math.isfinite(s) and s > 0
                else 1e-6 * max(abs(x0[name]), 1e-12)
            )
            hi, lo = f({**x0, name: x0[name] + h}), f({**x0, name: x0[name] - h})
            G[:, j] = [
                (float(hi.get(k, at[k])) - float(lo.get(k, at[k]))) / (2 * h) for k in outputs
            ]
        out: dict[str, float] = {}
        for key, g in zip(outputs, G, strict=True):
            idx = np.flatnonzero(g)
            if idx.size == 0:
                continue
            var = float(g[idx] @ self.matrix[np.ix_(idx, idx)] @ g[idx])
            out[key] = math.sqrt(max(var, 0.0)) if math.isfinite(var) else math.nan
        return out


def natural_covariance(
    names: Sequence[str],
    values: Sequence[float],
    jac: np.ndarray,
    residual: np.ndarray,
    bounds: Sequence[int],
    dnatural_dz: Sequence[float],
    ranges: Mapping[str, tuple[float, float]] | None = None,
    valid: np.ndarray | None = None,
    start_gain: np.ndarray | None = None,
) -> ParameterCovariance:
    """The covariance of the natural parameters from the optimiser's Jacobian.

    Parameters
    ----------
    names, values : sequence
        The fitted natural parameters and their values, one per column of ``jac``.
    jac : ndarray, shape (n, p)
        ``d residual / d z`` of the optimiser's parameters ``z`` at the solution.
    residual : ndarray, shape (n,)
        The residual at the solution.
    bounds : sequence of int
        Cumulative sizes of the chunks of ``residual`` (the noise of one is independent of the
        others': the simulation windows).
    dnatural_dz : sequence of float
        ``d natural / d z`` of each parameter (the chain rule; each natural parameter
        depends on its own ``z`` alone).
    ranges : mapping, optional
        The bounds of the effect parameters (:attr:`ParameterCovariance.ranges`).
    valid : ndarray of bool, shape (n,), optional
        Samples in the cost (all by default; ``jac``'s other rows are zero).
    start_gain : ndarray, shape (n,), optional
        The simulated output's sensitivity to the measured value its chunk starts from
        (:func:`~servobench.bench.identify.covariance.noise_model_covariance`).
    """
    J = np.asarray(jac, dtype=float) / np.asarray(dnatural_dz, dtype=float)
    r = np.asarray(residual, dtype=float)
    valid = np.ones(r.size, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    p = J.shape[1]
    norms = np.linalg.norm(J, axis=0)
    keep = np.flatnonzero(
        np.isfinite(norms)
        & (norms > NULL_COLUMN * max(float(np.nanmax(norms, initial=0.0)), 1e-300))
    )
    matrix = np.full((p, p), np.nan)
    n = int(valid.sum())
    if keep.size and n > keep.size:
        matrix[np.ix_(keep, keep)] = noise_model_covariance(
            J[:, keep], r, bounds, valid, start_gain
        )
    for i, name in enumerate(names):
        # a positive parameter whose first-order sigma exceeds its value is not determined: the
        # linear bar would reach below zero, and at a value near zero it is small for an error
        # in the factor (a B fitted to 1e-6 for 1.0 on a log as noisy as its signal)
        if name in POSITIVE and not math.sqrt(max(matrix[i, i], 0.0)) < abs(float(values[i])):
            matrix[i, :] = matrix[:, i] = np.nan
    ends = np.asarray(bounds, dtype=int)
    chunks = np.cumsum(valid)[ends - 1] if ends.size else None  # the chunks' ends in ``r[valid]``
    kept = r[valid]
    colour = residual_colour(kept, chunks) if kept.size > MIN_SAMPLES and np.any(kept) else None
    return ParameterCovariance(
        tuple(names), tuple(float(v) for v in values), matrix, colour, dict(ranges or {})
    )


def candidate_std(
    cand: Candidate,
    covariance: ParameterCovariance,
    quantities: Callable[[Candidate], Mapping[str, float]],
) -> dict[str, float]:
    """1-sigma of ``quantities(cand)`` (values computed from a candidate, by name) that the
    fitted parameters of ``covariance`` move; :meth:`ParameterCovariance.propagate`."""

    def at(x: Mapping[str, float]) -> Mapping[str, float]:
        base = dict(cand.base)
        effects = {name: dict(values) for name, values in cand.effects.items()}
        for key, value in x.items():
            name, _, pname = key.rpartition(".")
            if name:
                effects[name][pname] = value
            else:
                base[pname] = value
        return quantities(Candidate(base, effects))

    return covariance.propagate(at)

"""1-sigma of a diagnosed model's parameters, as the identification states them.

At the solution of a refit (:mod:`.refit`) the Jacobian of the training
residual with respect to the optimiser's parameters (``log M``, ``log B``, the
Coulomb levels and effect parameters scaled to order one) is taken to the
natural parameters by the chain rule and given to the HAC (Newey-West)
sandwich of :func:`servobench.bench.identify.covariance.hac_covariance`, lags
within each training window. The residual's whiteness
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
from servobench.bench.identify.covariance import ResidualColour, hac_covariance, residual_colour

#: Columns of the Jacobian smaller than this share of the largest are not determined by the data.
NULL_COLUMN = 1e-12
#: Step of the first-order propagation, in units of each parameter's sigma.
PROPAGATION_STEP = 1e-3
#: Fewest residual samples for the whiteness test.
MIN_SAMPLES = 8


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
        HAC covariance; NaN rows and columns for parameters the data do not determine.
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
        Cumulative sizes of the chunks of ``residual`` (lags stay within each).
    dnatural_dz : sequence of float
        ``d natural / d z`` of each parameter (the chain rule; each natural parameter
        depends on its own ``z`` alone).
    ranges : mapping, optional
        The bounds of the effect parameters (:attr:`ParameterCovariance.ranges`).
    """
    J = np.asarray(jac, dtype=float) / np.asarray(dnatural_dz, dtype=float)
    r = np.asarray(residual, dtype=float)
    p = J.shape[1]
    norms = np.linalg.norm(J, axis=0)
    keep = np.flatnonzero(
        np.isfinite(norms)
        & (norms > NULL_COLUMN * max(float(np.nanmax(norms, initial=0.0)), 1e-300))
    )
    matrix = np.full((p, p), np.nan)
    if keep.size and r.size > keep.size:
        matrix[np.ix_(keep, keep)] = hac_covariance(J[:, keep], r, bounds)
    colour = residual_colour(r, bounds) if r.size > MIN_SAMPLES and np.any(r) else None
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

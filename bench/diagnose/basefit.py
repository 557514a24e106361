"""Step 1: the base model, a linear block plus Coulomb friction per direction.

:func:`initial_base` is the one place that chooses where the starting values
come from: the project's identifier
(:func:`servobench.bench.identify.auto.identify_data`, on the same prepared
log) for open-loop logs, else -- or when the identifier gives up on the log --
an equation-error (inverse-dynamics) least-squares fit on the moving samples.
Either is only a start: :func:`fit_base` refits it on simulation error like
every candidate.
"""

from __future__ import annotations

import numpy as np

from servobench.bench.diagnose.data import DiagnosisData
from servobench.bench.diagnose.refit import FitResult, refit
from servobench.bench.diagnose.screening import screen_input
from servobench.bench.diagnose.simulate import Candidate
from servobench.bench.identify.auto import identify_data
from servobench.errors import IdentificationError
from servobench.sim_backend.physics.effects.spec import base_fit


def equation_error_base(data: DiagnosisData) -> dict[str, float]:
    """``M, B, coulomb_pos, coulomb_neg`` by equation error.

    ``u = M a + B v + coulomb_pos [v>0] - coulomb_neg [v<0]`` on the moving samples.
    """
    ctx = screen_input(
        data,
        Candidate({"M": 1.0, "B": 1.0, "coulomb_pos": 0.0, "coulomb_neg": 0.0}),
        [r.v for r in data.segments],
    )
    if int(ctx.moving.sum()) < 10:
        raise IdentificationError("too few samples in motion to identify the base model")
    coef, _ = base_fit(ctx)
    M, B, fcp, fcn = (float(c) for c in coef)
    if not (np.isfinite(coef).all() and M > 0 and B > 0):
        raise IdentificationError(
            f"the base fit is not physical (M = {M:.3g}, B = {B:.3g}): too little excitation?"
        )
    return {"M": M, "B": B, "coulomb_pos": max(fcp, 0.0), "coulomb_neg": max(fcn, 0.0)}


def initial_base(data: DiagnosisData) -> dict[str, float]:
    """Starting base model: the project's identifier on open-loop logs, else equation error."""
    if data.horizon_s is not None:  # closed loop: the identifier assumes open-loop runs
        return equation_error_base(data)
    try:
        model = identify_data(data.prepared).model
    except ValueError:  # IdentificationError, or a plant the identifier could not simulate
        return equation_error_base(data)
    base = {
        "M": float(model.M),
        "B": float(model.B),
        "coulomb_pos": max(float(model.coulomb_pos), 0.0),
        "coulomb_neg": max(float(model.coulomb_neg), 0.0),
    }
    if not (base["M"] > 0 and base["B"] > 0):
        return equation_error_base(data)
    return base


def fit_base(data: DiagnosisData) -> FitResult:
    """The base model refitted on simulation error (training samples)."""
    return refit(data, Candidate(initial_base(data)), bounds={})

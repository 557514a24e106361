"""Samples taken a known time after their command took force, moved back to the command's instant.

A free-running drive that receives the command and the feedback query one
after the other (the ODrive ASCII protocol: ``c 0 u`` then ``f 0``) applies
``u_k`` a lead ``d`` before it samples ``v_k``: the log's sample instants
are not the instants the commands changed, and the zero-order-hold models
(:mod:`servobench.bench.identify.regression`) would see a sliver ``d`` of
each new command inside the interval before it (at 200 Hz and 0.35 ms, M
comes out ~5 % low). The log says ``# command_lead_s = d`` (from
:meth:`servobench.drivers.base.Drive.command_lead_s`).

:func:`back_to_commands` undoes it with the model: over ``[t_k - d, t_k)``
only ``u_k`` acted, so by the exact first-order solution with the Coulomb
level of the direction of motion::

    v(t_k - d) = (v_k - (1 - e) / B * (u_k - F)) / e,    e = exp(-B d / M)

and the sample moves to ``t_k - d``, where the command interval starts. The
identification alternates it with the estimator (:data:`PASSES` times, from
the uncorrected estimate); ``d`` is a small share of the cycle, so each pass
shrinks the error by about that share.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from servobench.bench.identify.dataset import Dataset
from servobench.bench.model.servo import ServoModel

#: Correction passes (estimate, move the samples, estimate again).
PASSES = 3


def back_to_commands(data: Dataset, model: ServoModel, lead_s: float) -> Dataset:
    """``data`` with every sample moved back by ``lead_s`` [s] to its command's instant (see the module doc).

    Velocity-only: a log whose velocity was derived from position is returned as it is.
    """
    if lead_s <= 0 or data.derived:
        return data
    M, B = model.M, model.B
    e = math.exp(-B * lead_s / M)
    gain = (1.0 - e) / B
    segments = []
    for s in data.segments:
        u, v = s.u, s.v
        moving = np.sign(v)
        breaks = (v == 0) & ((u > model.coulomb_pos) | (u < -model.coulomb_neg))
        direction = np.where(moving != 0, moving, np.where(breaks, np.sign(u), 0.0))
        friction = np.where(direction > 0, model.coulomb_pos, np.where(direction < 0, -model.coulomb_neg, 0.0))
        v_back = np.where(direction != 0, (v - gain * (u - friction)) / e, 0.0)
        segments.append(replace(s, t=s.t - lead_s, v=v_back))
    return replace(data, segments=tuple(segments))


def lead_note(lead_s: float) -> str:
    return (
        f"each command took force {lead_s * 1e3:.3g} ms before its sample (command_lead_s): the samples "
        f"were moved back to the commands' instants with the model ({PASSES} passes)"
    )

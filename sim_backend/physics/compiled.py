"""A plant model as the compiled integrator reads it, and many models run in one call.

:func:`pack` turns a :class:`~servobench.sim_backend.physics.rich_plant.RichModel` into
:class:`Packed` numbers (the layout of :mod:`.kernels`), :func:`pack_coulomb` the base plant;
:func:`run` integrates a batch of them over windows of runs. A model whose terms are not all
data (a bare callable) does not pack: it runs on the reference loops. A spring carries the
modes of its systems for its reversals (a defective system's reversals run on its model's own
reference step, called back from the compiled loop).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from servobench.sim_backend.physics import kernels as k
from servobench.sim_backend.physics.effects.spec import GaussianExcess, SineForce, TableFriction


@dataclass(frozen=True)
class Packed:
    """One model's numbers (see :mod:`.kernels`), its delay in whole samples and its command
    transforms; ``ipar``'s offsets count from the model's own rows."""

    fpar: np.ndarray
    ipar: np.ndarray
    segs: np.ndarray
    table: np.ndarray
    forces: np.ndarray
    whole: int = 0
    inputs: tuple[Callable[[np.ndarray], np.ndarray], ...] = ()
    #: The model of a spring without modes (a defective system), whose reversals the compiled
    #: loop hands back to it.
    owner: object = None
    #: A spring's modes (:data:`.kernels.MODE_COLS` layout), shape (1, 6 * MODE_COLS); (0, ...)
    #: for other models and for a spring with a defective system.
    modes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6 * k.MODE_COLS), complex))

    def transform(self, line: np.ndarray) -> np.ndarray:
        """The command transforms applied to a command line (each is elementwise)."""
        for fn in self.inputs:
            line = fn(line)
        return np.ascontiguousarray(line, dtype=float)

    def line(self, u: np.ndarray) -> np.ndarray:
        """The line of a run simulated from its first sample with nothing applied before it:
        ``whole + 1`` zeros then ``u``, transformed. A window from sample ``s`` reads it from
        index ``s``, which is what priming with ``u[:s]`` gives the reference."""
        return self.transform(np.concatenate([np.zeros(self.whole + 1), np.asarray(u, float)]))


#: Keys of spring models in :data:`.kernels.REVERSALS`.
_KEYS = itertools.count(1)


def _ipar(kind: int, exc: bool, at: bool, segs: int, table: int, forces: int) -> np.ndarray:
    out = np.zeros(k.NI, dtype=np.int64)
    out[k.KIND], out[k.HAS_EXC], out[k.HAS_AT] = kind, int(exc), int(at)
    out[k.SEG1], out[k.TAB1], out[k.FOR1] = segs, table, forces
    out[k.MODE] = -1  # no modes (set where a spring has them)
    return out


def pack_coulomb(params, dt_s: float) -> Packed:
    """The base plant of :func:`~.coulomb.simulate_coulomb` (its effects ignored)."""
    fpar = np.zeros(k.NF)
    fpar[k.FCP], fpar[k.FCN] = params.coulomb_pos, params.coulomb_neg
    fpar[k.BKP], fpar[k.BKN] = params.breakaway_pos, params.breakaway_neg
    fpar[k.MASS], fpar[k.B_POS], fpar[k.B_NEG], fpar[k.DT] = params.M, params.B, params.B, dt_s
    return Packed(
        fpar, _ipar(k.COULOMB, False, False, 0, 0, 0), np.zeros((0, k.SEG_COLS)), np.zeros(0),
        np.zeros((0, 3)),
    )  # fmt: skip


def coupling_kind(coupling) -> int:
    """The integrator :mod:`.kernels` runs for a model's coupling (its ``terms.coupling``): one
    body without one, a play or a spring."""
    if coupling is None:
        return k.RIGID
    return k.GAP if coupling.kind == "gap" else k.SPRING


def pack(model, dt_s: float) -> Packed | None:
    """``model`` (a prepared :class:`~.rich_plant.RichModel`) over steps of ``dt_s``, or ``None``
    when one of its terms is not data."""
    terms = model.terms
    c = terms.coupling
    exc, at, forces = terms.friction_excess, terms.friction_at, terms.position_forces
    if (
        (exc is not None and not isinstance(exc, GaussianExcess))
        or (at is not None and not isinstance(at, TableFriction))
        or not all(isinstance(f, SineForce) for f in forces)
    ):
        return None
    fcp, fcn, bkp, bkn, _, _ = model.friction
    fpar = np.zeros(k.NF)
    fpar[k.FCP], fpar[k.FCN], fpar[k.BKP], fpar[k.BKN] = fcp, fcn, bkp, bkn
    if exc is not None:
        fpar[k.EXC_POS], fpar[k.EXC_NEG], fpar[k.EXC_INV] = exc.pos, exc.neg, exc.inv_speed
        # the excess is skipped where it cannot change the level; a table moves the level
        fpar[k.EXC_CUT] = math.inf if at is not None else k.excess_cut(exc.pos, exc.neg, fcp, fcn)
    table = np.zeros(0)
    if at is not None:
        fpar[k.AT_X0], fpar[k.AT_SCALE] = at.x0, at.scale
        table = np.array(at.values, dtype=float)
    if c is not None:
        fpar[k.HALF], fpar[k.RATIO] = 0.5 * c.gap, c.load_ratio
        fpar[k.STIFF], fpar[k.DAMP] = c.stiffness, c.damping
    fpar[k.MASS], fpar[k.B_POS], fpar[k.B_NEG], fpar[k.DT] = (
        model.params.M, model.B_pos, model.B_neg, dt_s,
    )  # fmt: skip
    segs = model.rows(dt_s)
    kind = coupling_kind(c)
    force_rows = np.array([(f.amp, f.k, f.phase) for f in forces], dtype=float).reshape(-1, 3)
    ipar = _ipar(kind, exc is not None, at is not None, len(segs), table.size, len(force_rows))
    owner, modes = None, np.zeros((0, 6 * k.MODE_COLS), complex)
    if kind == k.SPRING:
        modes = spring_modes(model)
        if modes.size:
            ipar[k.MODE] = 0  # the model's own row; :func:`run` sets the batch's
        else:  # a defective system: its reversals are handed back to the model
            ipar[k.KEY] = next(_KEYS)
            k.REVERSALS[int(ipar[k.KEY])] = owner = model
    inputs = tuple(fn for _, fn in sorted(terms.inputs, key=lambda item: item[0]))
    return Packed(
        fpar, ipar, segs, table, force_rows, model.whole_delay(dt_s), inputs, owner, modes
    )


#: A spring's systems ``(motor direction, load direction, motor held)`` in
#: :func:`.kernels.spring_system`'s order.
SPRING_SYSTEMS = ((1, 1, False), (1, -1, False), (-1, 1, False), (-1, -1, False), (1, 1, True), (1, -1, True))


def spring_modes(model) -> np.ndarray:
    """The modes of a spring model's six systems (:data:`.kernels.MODE_COLS` layout) from the
    :class:`~.bodies.Propagator` its reference integrator uses; empty when one is defective."""
    out = np.zeros((1, 6 * k.MODE_COLS), complex)
    for i, (sm, sl, held) in enumerate(SPRING_SYSTEMS):
        prop = model._spring_system(sm, sl, held)
        if not prop.ok:
            return out[:0]
        row = np.concatenate([prop.lam, prop.V.ravel(), prop.Vinv.ravel(), prop.Vinv_b])
        out[0, k.MODE_COLS * i : k.MODE_COLS * i + row.size] = row
    return out


def run(
    packs: Sequence[Packed],
    lines: Sequence[Sequence[np.ndarray]],
    windows: np.ndarray,
    start: np.ndarray,
    carry: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every model over every window in one compiled call.

    Parameters
    ----------
    packs : sequence of Packed, length P
    lines : sequence, per model, of one command line per run (:meth:`Packed.line`)
    windows : ndarray of int, shape (W, 4)
        Run, first sample (index in the run's line), samples, first output column.
    start : ndarray, shape (W, 5)
        The state at each window's start (motor ``v, x``, load ``v, x``, engaged side).
    carry : ndarray of bool, shape (W,), optional
        Windows that continue the one before them and carry on its second body
        (:func:`.kernels.carry_state`); none by default (each window starts relaxed at ``start``).

    Returns
    -------
    v, x : ndarray, shape (P, N)
        The measured body's velocity [units/s] and position [units] at each sample.
    final : ndarray, shape (P, W, 5)
        The state at each window's end.
    """
    P, runs = len(packs), len(lines[0]) if lines else 0
    if len(lines) != P:
        raise ValueError(f"{P} models need {P} sets of command lines, got {len(lines)}")
    ipar = np.array([pk.ipar for pk in packs], dtype=np.int64).reshape(P, k.NI)
    # each model's rows follow the ones before it in the shared arrays: offsets by running sums
    for first, last in ((k.SEG0, k.SEG1), (k.TAB0, k.TAB1), (k.FOR0, k.FOR1)):
        ends = np.cumsum(ipar[:, last] - ipar[:, first])
        offset = np.concatenate(([0], ends[:-1])) - ipar[:, first]
        ipar[:, first] += offset
        ipar[:, last] += offset
    has_modes = [pk.modes.size > 0 for pk in packs]
    if any(has_modes):
        rows = np.array([pk.modes.shape[0] for pk in packs])
        ipar[has_modes, k.MODE] = (np.cumsum(rows) - rows)[has_modes]
    # a line several models share (the same array: no command transform) is stored once
    line_at = np.empty((P, runs), dtype=np.int64)
    stored: dict[int, int] = {}
    unique: list[np.ndarray] = []
    line_next = 0
    for p, per_run in enumerate(lines):
        for r, ln in enumerate(per_run):
            at = stored.get(id(ln))
            if at is None:
                stored[id(ln)] = at = line_next
                unique.append(ln)
                line_next += ln.size
            line_at[p, r] = at
    windows = np.ascontiguousarray(windows, dtype=np.int64).reshape(-1, 4)
    n = int((windows[:, 3] + windows[:, 2]).max()) if windows.size else 0
    out_v, out_x = np.empty((P, n)), np.empty((P, n))
    final = np.empty((P, windows.shape[0], 5))
    k.run_batch(
        np.ascontiguousarray(np.stack([pk.fpar for pk in packs]).reshape(P, k.NF)),
        ipar,
        np.ascontiguousarray(np.concatenate([pk.segs for pk in packs]).reshape(-1, k.SEG_COLS)),
        np.ascontiguousarray(np.concatenate([pk.table for pk in packs]), dtype=float),
        np.ascontiguousarray(np.concatenate([pk.forces for pk in packs]).reshape(-1, 3)),
        np.ascontiguousarray(
            np.concatenate([pk.modes for pk in packs]).reshape(-1, 6 * k.MODE_COLS), dtype=complex
        ),
        np.concatenate(unique) if line_next else np.zeros(1),
        line_at,
        windows,
        np.ascontiguousarray(start, dtype=float).reshape(-1, 5),
        np.zeros(windows.shape[0], np.bool_) if carry is None else np.ascontiguousarray(carry, np.bool_),
        out_v,
        out_x,
        final,
    )
    return out_v, out_x, final

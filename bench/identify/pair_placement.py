"""Reads near a drive tick placed by the model's one-step pairs, where one request carries both.

Where one request carries the command and asks for the sample (Modbus FC23,
a CANopen SYNC, an EtherCAT frame: no command lead), a read taken at the
drive's tick ``k`` holds that tick's sample, and its command acts from tick
``k + 1``. The host knows the request's arrival only within its bracket
``t +- t_unc``; where a tick of the located grid lies inside it, the read may
belong to the tick before or after the one its logged instant gives
(:meth:`~servobench.bench.identify.drive_grid.DriveGrid.index`). Such a read,
misplaced by one tick, moves its sample and its command's action together,
which costs the fit wherever the axis is in a transient (a tick of a 10 ms
time constant is 2.5-10 % of a step at 0.25-1 ms).

:func:`place_by_pairs` decides each such read by the pairs around it: the
exact one-step response of the model (stick-slip, the command in force over
each tick) from the sample before to the read, and from the read to the
samples after, all reads of a run at once (dynamic programming along the
run). A change of shift between neighbouring reads costs
:data:`PAIR_DECISIVE` squared residual scales, so a stretch of reads moves
together; on a steady stretch every tick predicts alike and a read keeps its
logged one (where it costs nothing). A read the host stalled on is placed
alone among every tick its bracket holds.

Pure: arrays in, tick indices out; no transport.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from servobench.sim_backend.physics.kernels import stick_slip_step

#: A read's shift from its logged tick differing from the read before's costs this many residual
#: scales, squared: the shift changes only where the pairs then fit better by that much (a
#: three-sigma decision). The host's bracket sits off the drive's arrival alike for neighbouring
#: reads (a port's latency; a host cycle a whole number of ticks keeps their phase), so a stretch of
#: reads moves together at the cost of one change, however long.
PAIR_DECISIVE = 3.0
#: Each bracket widened by this share of the tick: the grid's phase on the host's clock is located
#: from the data, within a few microseconds (a read 2 us outside its bracket's tick was seen).
PHASE_SLACK = 0.05
#: Moving a read off its logged tick costs this share of that: where every tick fits alike (a steady
#: axis) the read keeps its logged one.
TIE_SHARE = 1e-3
#: The most ticks a read may move from its logged one (where its bracket holds them: a host that
#: stalled knows a read's instant only within several ticks).
MAX_SHIFT = 4


def place_by_pairs(
    t_s: np.ndarray,
    t_unc_s: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    k: np.ndarray,
    tick_instant,
    tick_s: float,
    params,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """The sample ticks ``k`` with each read whose bracket holds a tick decided by its pairs.

    All reads at once: each may take its logged tick or one up to
    :data:`MAX_SHIFT` ticks before or after it (where its bracket allows), and
    the ticks that leave the least sum of squared pair residuals, plus
    :data:`PAIR_DECISIVE` squared residual
    scales wherever a read's shift differs from the read before's, are found
    by dynamic programming along the run (a run of misplaced reads moves
    together, which one read at a time cannot: each alone agrees with its
    misplaced neighbours). A read whose bracket reaches further (the host
    stalled on it) then takes, of every tick its bracket holds, the one its
    own two pairs fit best, its neighbours as placed.

    Parameters
    ----------
    t_s, t_unc_s : ndarray, shape (n,)
        The reads' logged instants and half-brackets [s].
    u, v : ndarray, shape (n,)
        Command and velocity per read; ``u[i]`` acts from tick ``k[i] + 1``.
    k : ndarray, shape (n,)
        Each read's tick as its logged instant gives it (non-decreasing).
    tick_instant : callable
        Tick index -> its instant on the log's clock [s].
    tick_s : float
        The tick on the log's clock [s].
    params : PlantParams
        The model the pairs are judged under.
    rng : numpy.random.Generator, optional
        Instead of the least-cost ticks, one draw from their posterior under the pairs
        (:func:`_posterior_states`): each pair's residual normal with the residuals' robust
        scale, each change of shift as unlikely as its cost says, a stalled read's ticks weighed
        by its two pairs. The timing figure's draws: a read the pairs decide keeps its tick, one
        they leave in doubt moves as often as its odds say.

    Returns
    -------
    ndarray, shape (n,)
        The ticks, non-decreasing.
    """
    t = np.asarray(t_s, dtype=float)
    unc = np.asarray(t_unc_s, dtype=float)
    u = np.asarray(u, dtype=float)
    v = np.asarray(v, dtype=float)
    k = np.asarray(k, dtype=float)
    n = k.size
    if n < 3:
        return k.copy()
    unc = unc + PHASE_SLACK * tick_s  # the grid's phase is located only so well
    reach = int(np.clip(np.ceil(2.0 * float(np.quantile(unc, 0.99)) / tick_s), 1, MAX_SHIFT))
    shifts = np.arange(-reach, reach + 1, dtype=float)
    first = np.floor(_tick_at(tick_instant, k, t - unc))
    last = np.floor(_tick_at(tick_instant, k, t + unc))
    wide = (first < k - reach) | (last > k + reach)  # the host stalled on it: placed alone
    centre = k.copy()
    scale = None
    for judged in (False, True):  # the stalled reads' pairs left out, then judged where they were put
        cand = centre[:, None] + shifts[None, :]  # (n, S)
        allowed = (tick_instant(cand) <= t[:, None] + unc[:, None]) & (
            tick_instant(cand + 1.0) > t[:, None] - unc[:, None])  # fmt: skip
        allowed[:, reach] = True  # the logged tick itself (a stalled read: where it was put)
        allowed[wide] = shifts == 0.0
        if allowed.sum() == n and not wide.any():
            return k.copy()
        u_first = np.concatenate(([0.0], u[:-2]))  # pair (j - 1, j): over its first tick, u[j - 2]
        e = _allowed_pair_errors(cand, allowed, v, u_first, u[:-1], tick_s, params)
        if scale is None:
            steps = np.diff(k) > 0
            # none where no pair a tick apart stands clear of the stalled reads
            kept = e[:, reach, reach][steps & ~wide[1:] & ~wide[:-1]]
            scale = 1.4826 * float(np.median(np.abs(kept))) if kept.size else 0.0
            if not scale > 0:
                return k.copy()
        if not judged:
            e[wide[:-1] | wide[1:]] = 0.0
        bar = (PAIR_DECISIVE * scale) ** 2
        if rng is None:
            placed = _viterbi(cand, allowed, e, shifts, bar)
            _place_alone(np.flatnonzero(wide), placed, first, last, u, v, tick_s, *_plant(params))
        else:
            placed = _posterior(cand, allowed, e, shifts, bar, 2.0 * scale * scale, rng)
            _alone(np.flatnonzero(wide), placed, first, last, u, v, tick_s, *_plant(params),
                   2.0 * scale * scale, rng.random(int(wide.sum())))  # fmt: skip
        if not wide.any():
            break
        centre = np.where(wide, placed, k)
    return placed


def _viterbi(cand: np.ndarray, allowed: np.ndarray, e: np.ndarray, shifts: np.ndarray, bar: float) -> np.ndarray:
    """The ticks of ``cand`` (n, S), one per read among the ``allowed``, that leave the least sum of
    the squared pair residuals ``e`` (n - 1, S, S), ``bar`` per change of shift between reads and
    :data:`TIE_SHARE` of it per read off its logged tick (``shifts`` 0)."""
    n, size = cand.shape
    moved, switch, pair = _viterbi_costs(cand, e, shifts, bar)
    state = _viterbi_states(
        np.ascontiguousarray(pair, dtype=float),
        np.ascontiguousarray(switch, dtype=float),
        np.ascontiguousarray(allowed, dtype=np.bool_),
        np.ascontiguousarray(moved, dtype=float),
    )
    return cand[np.arange(n), state]


def _viterbi_costs(
    cand: np.ndarray, e: np.ndarray, shifts: np.ndarray, bar: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_viterbi`'s costs: per candidate off its logged tick (S,), per change of shift
    between reads (S, S), and per pair of reads (n - 1, S, S: never back in time)."""
    moved = TIE_SHARE * bar * (shifts != 0.0)
    switch = bar * (shifts[:, None] != shifts[None, :])
    pair = np.where(cand[:-1, :, None] <= cand[1:, None, :], e * e, np.inf)
    return moved, switch, pair


@njit(cache=True)
def _viterbi_states(pair, switch, allowed, moved):
    """The least-cost path's state per read: ``cost_j(b) = min_a cost_{j-1}(a) + pair[j-1, a, b] +
    switch[a, b]``, plus ``moved[b]`` where ``allowed[j, b]`` (else infinite); the first of equal
    minima, NaN first (``np.argmin``'s choice)."""
    n1, size = pair.shape[0], pair.shape[1]
    cost = np.empty(size)
    for b in range(size):
        cost[b] = moved[b] if allowed[0, b] else np.inf
    back = np.zeros((n1, size), dtype=np.int64)
    new = np.empty(size)
    for j in range(1, n1 + 1):
        for b in range(size):
            best, arg = cost[0] + pair[j - 1, 0, b] + switch[0, b], 0
            for a in range(1, size):
                total = cost[a] + pair[j - 1, a, b] + switch[a, b]
                if total < best or (total != total and best == best):
                    best, arg = total, a
            back[j - 1, b] = arg
            new[b] = best + (moved[b] if allowed[j, b] else np.inf)
        for b in range(size):
            cost[b] = new[b]
    state = np.empty(n1 + 1, dtype=np.int64)
    best, arg = cost[0], 0
    for b in range(1, size):
        if cost[b] < best or (cost[b] != cost[b] and best == best):
            best, arg = cost[b], b
    state[n1] = arg
    for j in range(n1, 0, -1):
        state[j - 1] = back[j - 1, state[j]]
    return state


def _posterior(cand: np.ndarray, allowed: np.ndarray, e: np.ndarray, shifts: np.ndarray, bar: float,
               temperature: float, rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """One path of ticks of ``cand`` drawn from the posterior whose negative log is :func:`_viterbi`'s
    cost over ``temperature`` (twice the pairs' residual variance: each residual normal), by
    forward filtering and backward sampling; :func:`_viterbi` gives this posterior's mode."""
    n, size = cand.shape
    moved, switch, pair = _viterbi_costs(cand, e, shifts, bar)
    state = _posterior_states(
        np.ascontiguousarray(pair, dtype=float) / temperature,
        np.ascontiguousarray(switch, dtype=float) / temperature,
        np.ascontiguousarray(allowed, dtype=np.bool_),
        np.ascontiguousarray(moved, dtype=float) / temperature,
        rng.random(n),
    )
    return cand[np.arange(n), state]


@njit(cache=True)
def _posterior_states(pair, switch, allowed, moved, uniform):  # pragma: no cover - compiled
    """A state per read drawn from ``p(path) ~ exp(-sum(moved[s_j]) - sum(pair[j - 1, s_{j-1}, s_j]
    + switch[s_{j-1}, s_j]))`` over the ``allowed`` states (costs already over the temperature):
    forward log-weights, then each state from the last back, given the one after it, by inverting
    its cumulative weight at ``uniform[j]``."""
    n1, size = pair.shape[0], pair.shape[1]
    n = n1 + 1
    alpha = np.full((n, size), -np.inf)
    for b in range(size):
        if allowed[0, b]:
            alpha[0, b] = -moved[b]
    for j in range(1, n):
        for b in range(size):
            if not allowed[j, b]:
                continue
            top = -np.inf
            for a in range(size):
                w = alpha[j - 1, a] - pair[j - 1, a, b] - switch[a, b]
                if w > top:
                    top = w
            if top == -np.inf:
                continue
            total = 0.0
            for a in range(size):
                total += np.exp(alpha[j - 1, a] - pair[j - 1, a, b] - switch[a, b] - top)
            alpha[j, b] = top + np.log(total) - moved[b]
    state = np.empty(n, dtype=np.int64)
    logw = np.empty(size)
    for j in range(n - 1, -1, -1):
        for a in range(size):
            logw[a] = alpha[j, a] if j == n - 1 else alpha[j, a] - pair[j, a, state[j + 1]] - switch[a, state[j + 1]]
        pick = _pick(logw, uniform[j])
        if pick < 0:  # nothing reaches the state after (cannot happen on an allowed path)
            pick = 0
            for a in range(size):
                if allowed[j, a]:
                    pick = a
                    break
        state[j] = pick
    return state


def _viterbi_reference(cand: np.ndarray, allowed: np.ndarray, e: np.ndarray, shifts: np.ndarray, bar: float) -> np.ndarray:
    """:func:`_viterbi` in numpy, one read at a time (what the compiled path is tested against)."""
    n, size = cand.shape
    moved, switch, pair = _viterbi_costs(cand, e, shifts, bar)
    cost = np.where(allowed[0], moved, np.inf)
    back = np.zeros((n - 1, size), dtype=int)
    for j in range(1, n):
        total = cost[:, None] + pair[j - 1] + switch
        back[j - 1] = np.argmin(total, axis=0)
        cost = total[back[j - 1], np.arange(size)] + np.where(allowed[j], moved, np.inf)
    state = np.empty(n, dtype=int)
    state[-1] = int(np.argmin(cost))
    for j in range(n - 1, 0, -1):
        state[j - 1] = back[j - 1, state[j]]
    return cand[np.arange(n), state]


def _tick_at(tick_instant, k: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The (fractional) tick index of instants ``t`` [s], near ticks ``k`` (the grid is linear)."""
    at, step = tick_instant(k), tick_instant(k + 1.0) - tick_instant(k)
    return k + (t - at) / step


def _plant(params) -> tuple[float, float, float, float, float, float]:
    """``(M, B, coulomb_pos, coulomb_neg, breakaway_pos, breakaway_neg)`` of ``params``, as floats."""
    return (float(params.M), float(params.B), float(params.coulomb_pos), float(params.coulomb_neg),
            float(params.breakaway_pos), float(params.breakaway_neg))  # fmt: skip


@njit(cache=True, error_model="numpy")
def _place_alone(wide, k, first, last, u, v, tick_s, M, B, fcp, fcn, bkp, bkn):
    """Each stalled read ``wide[j]`` (ascending) placed in ``k`` in turn, as :func:`_best_alone`
    places it: of ticks ``first`` to ``last`` within its neighbours' (the one before as placed), the
    one its two pairs fit best, the first of equal costs. Compiled: a loaded host stalls on
    thousands of reads, and each is placed alone (numpy on a handful of ticks per read cost a
    served CANopen run 30 s)."""
    _alone(wide, k, first, last, u, v, tick_s, M, B, fcp, fcn, bkp, bkn, 0.0, np.empty(0))


@njit(cache=True, error_model="numpy")
def _alone(wide, k, first, last, u, v, tick_s, M, B, fcp, fcn, bkp, bkn, temperature, uniform):
    """Each stalled read ``wide[j]`` placed in turn among the ticks its bracket and its neighbours
    allow: the best (``temperature`` 0: :func:`_place_alone`), or one drawn with weights
    ``exp(-cost / temperature)`` by ``uniform[j]`` (the timing figure's draws)."""
    n = k.size
    for j in range(wide.size):
        i = wide[j]
        lo = first[i] if i == 0 else max(first[i], k[i - 1])
        hi = last[i] if i + 1 >= n else min(last[i], k[i + 1])
        if not lo <= hi:
            continue
        count = int(hi - lo) + 1
        costs = np.empty(count)
        for m in range(count):
            costs[m] = _alone_cost(i, lo + m, k, u, v, tick_s, M, B, fcp, fcn, bkp, bkn)
        pick = _least(costs) if temperature <= 0.0 else _drawn(costs, temperature, uniform[j])
        if pick >= 0:
            k[i] = lo + pick


@njit(cache=True)
def _least(costs):
    """The index of the least cost, the first of equal ones, a NaN first (``np.argmin``'s choice)."""
    best, arg = np.inf, 0
    for m in range(costs.size):
        cost = costs[m]
        if cost < best or (cost != cost and best == best):
            best, arg = cost, m
    return arg


@njit(cache=True)
def _drawn(costs, temperature, uniform):
    """An index drawn with weights ``exp(-(cost - least) / temperature)`` (NaN weighs nothing) by
    :func:`_pick`; -1 where no cost is finite."""
    best = np.inf
    for m in range(costs.size):
        if costs[m] < best:
            best = costs[m]
    logw = np.empty(costs.size)
    for m in range(costs.size):
        logw[m] = -(costs[m] - best) / temperature if costs[m] == costs[m] else -np.inf
    return _pick(logw, uniform) if best < np.inf else -1


@njit(cache=True)
def _pick(logw, uniform):
    """An index drawn with weights ``exp(logw)`` by inverting their cumulative sum at ``uniform``
    (in [0, 1)); -1 where every weight is 0 (``logw`` all -inf)."""
    top = -np.inf
    for a in range(logw.size):
        if logw[a] > top:
            top = logw[a]
    if top == -np.inf:
        return -1
    weights = np.empty(logw.size)
    total = 0.0
    for a in range(logw.size):
        weights[a] = np.exp(logw[a] - top)
        total += weights[a]
    pick, run = logw.size - 1, 0.0
    for a in range(logw.size):
        run += weights[a]
        if uniform * total < run:
            pick = a
            break
    while weights[pick] == 0.0 and pick > 0:  # rounding at the top of the cumulative weight
        pick -= 1
    return pick


@njit(cache=True, error_model="numpy")
def _alone_cost(i, c, k, u, v, tick_s, M, B, fcp, fcn, bkp, bkn):
    """The squared residuals of read ``i``'s two pairs with it at tick ``c``, its neighbours at
    theirs in ``k`` (compiled; what :func:`_place_alone` minimises and :func:`_alone`
    weighs)."""
    n = k.size
    cost = 0.0
    if i > 0:
        before = u[i - 2] if i >= 2 else 0.0
        e = _pair_error1(k[i - 1], c, v[i - 1], v[i], before, u[i - 1], tick_s, M, B, fcp, fcn, bkp, bkn)
        cost += e * e
    if i + 1 < n:
        prior = u[i - 1] if i >= 1 else 0.0
        e = _pair_error1(c, k[i + 1], v[i], v[i + 1], prior, u[i], tick_s, M, B, fcp, fcn, bkp, bkn)
        cost += e * e
    return cost


@njit(cache=True, error_model="numpy")
def _pair_error1(k_a, k_b, v_a, v_b, u_first, u_rest, tick_s, M, B, fcp, fcn, bkp, bkn):
    """:func:`_pair_errors` of one pair (compiled), by the base plant's compiled step."""
    ticks = k_b - k_a
    mid = stick_slip_step(v_a, u_first, tick_s if ticks >= 1 else 0.0, M, B, fcp, fcn, bkp, bkn)
    return v_b - stick_slip_step(mid, u_rest, max(ticks - 1.0, 0.0) * tick_s, M, B, fcp, fcn, bkp, bkn)


def _best_alone(i: int, k: np.ndarray, first: float, last: float, u: np.ndarray, v: np.ndarray,
                tick_s: float, params) -> float:  # fmt: skip
    """Of ticks ``first`` to ``last`` (within its neighbours'), the one read ``i``'s two pairs fit best
    (numpy, one read: what the compiled :func:`_place_alone` is tested against)."""
    lo = max(first, k[i - 1] if i > 0 else -np.inf)
    hi = min(last, k[i + 1] if i + 1 < k.size else np.inf)
    if not lo <= hi:
        return float(k[i])
    c = np.arange(lo, hi + 1.0)
    cost = np.zeros(c.size)
    if i > 0:
        before = u[i - 2] if i >= 2 else 0.0
        e = _pair_errors(np.full(c.size, k[i - 1]), c, np.full(c.size, v[i - 1]), np.full(c.size, v[i]),
                         np.full(c.size, before), np.full(c.size, u[i - 1]), tick_s, params)  # fmt: skip
        cost += e * e
    if i + 1 < k.size:
        e = _pair_errors(c, np.full(c.size, k[i + 1]), np.full(c.size, v[i]), np.full(c.size, v[i + 1]),
                         np.full(c.size, u[i - 1] if i >= 1 else 0.0), np.full(c.size, u[i]), tick_s, params)  # fmt: skip
        cost += e * e
    return float(c[int(np.argmin(cost))])


def _allowed_pair_errors(cand: np.ndarray, allowed: np.ndarray, v: np.ndarray, u_first: np.ndarray,
                         u_rest: np.ndarray, tick_s: float, params) -> np.ndarray:  # fmt: skip
    """:func:`_pair_errors` of every pair of neighbouring reads' candidates ``cand`` (n, S), shape
    (n - 1, S, S), computed only where both candidates are ``allowed`` (a read's bracket holds a
    few of the S ticks, so most pairs are never a path's); 0 elsewhere, which no least-cost path
    reads (:func:`_viterbi` adds it to an infinite cost). Compiled; equal to :func:`_pair_errors`
    within rounding (a few units in the last place: the C library's exp and log against numpy's)."""
    return _allowed_pair_errors_c(np.ascontiguousarray(cand, dtype=float), np.ascontiguousarray(allowed, dtype=np.bool_),
                                  np.asarray(v, dtype=float), np.asarray(u_first, dtype=float),
                                  np.asarray(u_rest, dtype=float), float(tick_s), *_plant(params))  # fmt: skip


@njit(cache=True, error_model="numpy")
def _allowed_pair_errors_c(cand, allowed, v, u_first, u_rest, tick_s, M, B, fcp, fcn, bkp, bkn):
    """:func:`_allowed_pair_errors`, compiled: a log's placement runs it tens of times over
    thousands of reads (numpy's temporaries over every allowed pair were a sixth of a served run's
    identification)."""
    n, size = cand.shape
    e = np.zeros((n - 1, size, size))
    for j in range(n - 1):
        for a in range(size):
            if not allowed[j, a]:
                continue
            for b in range(size):
                if allowed[j + 1, b]:
                    e[j, a, b] = _pair_error1(cand[j, a], cand[j + 1, b], v[j], v[j + 1], u_first[j], u_rest[j],
                                              tick_s, M, B, fcp, fcn, bkp, bkn)  # fmt: skip
    return e


def _pair_errors(k_a, k_b, v_a, v_b, u_first, u_rest, tick_s: float, params) -> np.ndarray:
    """Residuals of pairs of samples ``v_a`` at ticks ``k_a`` and ``v_b`` at ``k_b`` (broadcast;
    the leading axis is the pair's): ``v_b`` less the model's exact stick-slip response from
    ``v_a`` under ``u_first`` over the first tick and ``u_rest`` over the others. Two reads of one
    tick hold one sample (residual ``v_b - v_a``). Numpy: the reference the compiled
    :func:`_pair_error1` (the placement's path) is tested against, with :func:`_best_alone`."""
    shape = np.broadcast_shapes(np.shape(k_a), np.shape(k_b))
    ticks = np.broadcast_to(k_b - k_a, shape)
    ones = np.ones(shape)
    col = (slice(None),) + (None,) * (len(shape) - 1)
    va, vb = v_a[col] * ones, v_b[col] * ones
    mid = _step(va, u_first[col] * ones, np.where(ticks >= 1, tick_s, 0.0), params)
    end = _step(mid, u_rest[col] * ones, np.maximum(ticks - 1.0, 0.0) * tick_s, params)
    return vb - end


def _step(v: np.ndarray, u: np.ndarray, dt: np.ndarray, params) -> np.ndarray:
    """The exact stick-slip velocity after ``dt`` [s] under a constant command ``u`` from ``v``
    (elementwise; the piecewise exponential of
    :func:`~servobench.bench.identify.simulation.simulate_variable_dt`)."""
    M, B = params.M, params.B
    fcp, fcn = params.coulomb_pos, params.coulomb_neg
    bkp, bkn = params.breakaway_pos, params.breakaway_neg
    tau = M / B
    forward = (v > 0) | ((v == 0) & (u > bkp))
    backward = (v < 0) | ((v == 0) & (u < -bkn))
    f = np.where(forward, fcp, -fcn)
    vinf = (u - f) / B
    vn = vinf + (v - vinf) * np.exp(-dt / tau)
    keeps = np.where(forward, vn > 0, vn < 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = tau * np.log((v - vinf) / -vinf)
    sticks = (-bkn <= u) & (u <= bkp)
    f2 = np.where(u > bkp, fcp, -fcn)
    after = np.where(sticks, 0.0, (u - f2) / B * (1.0 - np.exp(-(dt - tc) / tau)))
    moving = forward | backward
    return np.where(moving & keeps, vn, np.where(moving, after, 0.0))

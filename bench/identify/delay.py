"""The drive's action delay: commands that act ``delay_s`` after their logged instants.

A drive that runs its own control tick samples at its last tick and acts at
its next one, so a command ``u[k]`` logged at ``t_k`` acts over
``[t_k + d, t_{k+1} + d)`` (``d``: :attr:`~servobench.bench.model.servo.ServoModel.delay_s`,
the sample's lag included). Between two sample instants the plant then
sees a staircase of the commands whose switch instants ``t_j + d`` fall
inside the interval, and the one in force before the first of them.

This module turns such a log into what the zero-order-hold machinery
already handles, exactly:

* :func:`merged_grid` -- the sample instants and the switch instants in one
  grid, with the command in force over each of its intervals; a simulation
  on it (any exact stick-slip integrator with per-interval steps) taken
  back at the sample rows is the delayed plant's response;
* :func:`effective_command` -- per sample interval, the one constant command
  that moves a first-order block of time constant ``tau_s`` exactly as the
  staircase does: ``v[k+1] = a v[k] + b (u_eff[k] - F)`` while the velocity
  keeps its sign, so the exact pair regression holds with ``u_eff`` for ``u``.

Where each row's command acts at an instant of its own (a drive whose
commands and samples go in separate requests: a command acts at the drive's
tick after it arrives, its sample was taken at the tick before the query),
``offsets_s`` moves each switch by its own amount on top of the delay: ``u[k]``
acts from ``t_k + d + offsets_s[k]`` (zero-mean offsets keep ``d`` the mean
action delay). A later command never acts before an earlier one.

Before the first command acts, ``u_before`` is in force (0 for a run that
starts from an enabled axis at rest). Switch instants within
:data:`COINCIDE` of a cycle of a sample instant are taken to fall on it, so a
whole-cycle delay gives no sliver intervals.
"""

from __future__ import annotations

import numpy as np

#: Switch instants this close to a sample instant (share of the mean interval) fall on it.
COINCIDE = 1e-9


def sample_instants(n: int, dt_s: float | np.ndarray) -> np.ndarray:
    """The ``n`` sample instants [s] from 0, for one interval or one per interval."""
    if np.ndim(dt_s) == 0:
        return np.arange(n, dtype=float) * float(dt_s)
    return np.concatenate(([0.0], np.cumsum(np.asarray(dt_s, dtype=float))))


def merged_grid(
    u: np.ndarray,
    dt_s: float | np.ndarray,
    delay_s: float,
    u_before: float = 0.0,
    offsets_s: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(u_m, dt_m, rows)``: the commands in force over a grid of the sample and switch instants.

    Parameters
    ----------
    u : ndarray, shape (n,)
        Commands as logged [command units]; ``u[k]`` acts from ``t_k + delay_s``.
    dt_s : float or ndarray of shape (n - 1,)
        Sample interval(s) [s].
    delay_s : float
        Action delay [s]; negative: the command acts before its logged instant.
    u_before : float
        Command in force before ``u[0]`` acts.
    offsets_s : ndarray of shape (n,), optional
        Each row's own shift of its switch [s] on top of ``delay_s`` (see the module doc).

    Returns
    -------
    u_m : ndarray, shape (N,)
        Command in force from each grid instant to the next.
    dt_m : ndarray, shape (N - 1,)
        The grid's intervals [s].
    rows : ndarray of int, shape (n,)
        The grid index of each sample instant.
    """
    u = np.asarray(u, dtype=float)
    n = u.size
    t = sample_instants(n, dt_s)
    if n == 0:
        return u.copy(), np.zeros(0), np.zeros(0, dtype=int)
    mean_dt = float(t[-1] / (n - 1)) if n > 1 else 1.0
    eps = COINCIDE * mean_dt
    switches = switch_instants(t, delay_s, offsets_s)
    # switches that fall on a sample instant (within eps) add no grid point
    inside = switches < t[-1] - eps
    s_in = switches[inside]
    near = np.searchsorted(t, s_in)
    lo = np.abs(s_in - t[np.clip(near - 1, 0, n - 1)])
    hi = np.abs(t[np.clip(near, 0, n - 1)] - s_in)
    extra = s_in[np.minimum(lo, hi) > eps]
    grid = np.concatenate((t, extra))
    order = np.argsort(grid, kind="stable")
    grid = grid[order]
    rows = np.flatnonzero(order < n)
    # the command in force from each grid instant: the last switch at or before it
    j = np.searchsorted(switches, grid + eps, side="right") - 1
    u_m = np.where(j >= 0, u[np.clip(j, 0, n - 1)], float(u_before))
    return u_m, np.diff(grid), rows


def switch_instants(t_s: np.ndarray, delay_s: float, offsets_s: np.ndarray | None = None) -> np.ndarray:
    """The instants [s] the commands logged at ``t_s`` act from: ``t_s + delay_s``, each moved by its
    offset where given, never before an earlier row's (a later command cannot act first)."""
    switches = np.asarray(t_s, dtype=float) + float(delay_s)
    if offsets_s is None:
        return switches
    return np.maximum.accumulate(switches + np.asarray(offsets_s, dtype=float))


def effective_command(
    u: np.ndarray,
    dt_s: float | np.ndarray,
    delay_s: float,
    tau_s: float,
    u_before: float = 0.0,
    offsets_s: np.ndarray | None = None,
) -> np.ndarray:
    """Per sample interval, the constant command equivalent to the delayed staircase, shape ``(n - 1,)``.

    Over interval ``k`` the pieces ``p`` of :func:`merged_grid` act with weights
    ``exp(-(t_{k+1} - end_p)/tau) - exp(-(t_{k+1} - start_p)/tau)`` (the share
    of the step response each contributes at ``t_{k+1}``); ``u_eff[k]`` is
    their weighted mean. Exact for a first-order block of time constant
    ``tau_s`` [s] while the friction force stays constant over the interval.
    With ``delay_s`` 0 it is ``u[:-1]``. A negative delay (a command that acts before
    its logged instant) is handled alike, and so are per-row ``offsets_s`` [s].
    """
    u = np.asarray(u, dtype=float)
    n = u.size
    if n < 2:
        return u[:0].copy()
    if delay_s == 0 and offsets_s is None:
        return u[:-1].copy()
    if np.ndim(dt_s) == 0 and offsets_s is None:
        return _effective_regular(u, float(dt_s), delay_s, tau_s, u_before)
    u_m, dt_m, rows = merged_grid(u, dt_s, delay_s, u_before, offsets_s)
    grid = np.concatenate(([0.0], np.cumsum(dt_m)))
    # each grid interval i belongs to sample interval k(i); its end relative to t_{k+1}
    k_of = np.searchsorted(rows, np.arange(grid.size - 1), side="right") - 1
    t_end_k = grid[rows[1:]][k_of]
    w = np.exp(-(t_end_k - grid[1:]) / tau_s) - np.exp(-(t_end_k - grid[:-1]) / tau_s)
    num = np.add.reduceat(w * u_m[:-1], rows[:-1])
    den = np.add.reduceat(w, rows[:-1])
    if not np.all(den > 0):  # a time constant so long the weights round to 0 (B = 0): their
        # limit, the pieces weighted by their durations
        num_t, den_t = np.add.reduceat(dt_m * u_m[:-1], rows[:-1]), np.add.reduceat(dt_m, rows[:-1])
        num, den = np.where(den > 0, num, num_t), np.where(den > 0, den, den_t)
    out = np.where(den > 0, num / np.where(den > 0, den, 1.0), u_m[rows[:-1]])
    return out


def _effective_regular(u: np.ndarray, dt_s: float, delay_s: float, tau_s: float, u_before: float) -> np.ndarray:
    """:func:`effective_command` on one sample interval ``dt_s`` without offsets: with
    ``delay_s = (m + f) dt_s`` (:func:`split_delay`) interval ``k`` holds ``u[k - m - 1]`` for
    ``f dt_s`` and then ``u[k - m]`` (only ``u[k - m]`` where ``f`` is 0), so ``u_eff`` is their
    mean with the weights ``exp(-(1 - f) dt/tau) - exp(-dt/tau)`` and ``1 - exp(-(1 - f) dt/tau)``
    (``u_before`` before ``u[0]``; the last command stays in force past ``u[-1]``)."""
    m, f = split_delay(delay_s, dt_s)
    n = u.size
    padded = np.concatenate(([float(u_before)], u))  # padded[j + 1] = u[j], padded[0]: before
    k = np.arange(n - 1)
    now = padded[np.clip(k - m, -1, n - 1) + 1]
    if f == 0.0:
        return now
    before = padded[np.clip(k - m - 1, -1, n - 1) + 1]
    late = np.exp(-(1.0 - f) * dt_s / tau_s)
    w_before, w_now = late - np.exp(-dt_s / tau_s), 1.0 - late
    if not w_before + w_now > 0.0:  # a time constant so long the weights round to 0 (B = 0)
        w_before, w_now = f, 1.0 - f  # their limit
    return (w_before * before + w_now * now) / (w_before + w_now)


def split_delay(delay_s: float, dt_s: float) -> tuple[int, float]:
    """``delay_s = (m + f) dt_s``: the whole cycles ``m`` and the fraction ``0 <= f < 1``."""
    cycles = float(delay_s) / float(dt_s)
    m = int(np.floor(cycles + COINCIDE))
    f = max(0.0, cycles - m)
    return m, (0.0 if f < COINCIDE else f)

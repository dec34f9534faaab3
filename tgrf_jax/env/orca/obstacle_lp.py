"""The obstacle lines in the linear programs: RVO2 puts them first, so they never enter the (L, P) line tables;
small loops up to the largest obstacle line count walk them (linearProgram2), give every later line the interval
they leave it (linearProgram1) and minimise their penetration (linearProgram3)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from tgrf_jax.env.orca.linear_program import _lp1_optimum, _lp2_start
from tgrf_jax.env.orca.numerics import RVO_EPSILON, _det, _safe_sqrt


class _ObstacleLP(NamedTuple):
    """The obstacle lines of every problem: (K, P) tables whose first ``count`` (P,) rows hold them in
    RVO2's order, and linearProgram1's interval on each (from the velocity disk and the obstacle lines
    before it; ok: linearProgram1 succeeds).

    ``cols``: None, or the problems (C,) of a linearProgram3 chunk, whose ``count`` (C,) this then holds:
    the tables stay every problem's and each row is read for the chunk's problems only when a loop reaches
    it.  Gathering whole (K, C) tables instead, every round, would cost more than the rounds themselves (K is
    the edge capacity; the loops stop at the chunk's largest count, a few lines)."""

    px: jax.Array
    py: jax.Array
    dx: jax.Array
    dy: jax.Array
    count: jax.Array
    t_left: jax.Array
    t_right: jax.Array
    ok: jax.Array
    cols: jax.Array | None = None

    def line(self, i):
        """(px, py, dx, dy) of row i."""
        return self._read((self.px, self.py, self.dx, self.dy), i)

    def interval(self, i):
        """(t_left, t_right, ok) of row i."""
        return self._read((self.t_left, self.t_right, self.ok), i)

    def _read(self, tables, i):
        rows = _row(tables, i)
        return rows if self.cols is None else tuple(x[self.cols] for x in rows)


def _row(tables, i):
    return tuple(lax.dynamic_index_in_dim(x, i, 0, keepdims=False) for x in tables)


def _interval_update(bounds, pix, piy, dix, diy, pjx, pjy, djx, djy, use):
    """linearProgram1's step on line i for an earlier line j (where ``use``): bounds = (t_left, t_right,
    bad), bad where RVO2 returns false for a parallel line on the wrong side."""
    t_left, t_right, bad = bounds
    den = _det(dix, diy, djx, djy)
    num = _det(djx, djy, pix - pjx, piy - pjy)
    parallel = jnp.abs(den) <= RVO_EPSILON
    t = num / jnp.where(parallel, 1.0, den)
    t_right = jnp.where(use & ~parallel & (den >= 0.0), jnp.minimum(t_right, t), t_right)
    t_left = jnp.where(use & ~parallel & (den < 0.0), jnp.maximum(t_left, t), t_left)
    return t_left, t_right, bad | (use & parallel & (num < 0.0))


def _obstacle_lp(lines, count, radius) -> _ObstacleLP:
    """:class:`_ObstacleLP` of the obstacle lines (4 x (K, P), count (P,)); radius (P,): the disk."""

    def interval(i, tables):
        pix, piy, dix, diy = _row(lines, i)
        dot = pix * dix + piy * diy
        disc = dot * dot + radius * radius - (pix * pix + piy * piy)
        sq = _safe_sqrt(disc)
        t_left, t_right, bad = lax.fori_loop(
            0,
            i,
            lambda j, b: _interval_update(b, pix, piy, dix, diy, *_row(lines, j), True),
            (-dot - sq, -dot + sq, disc < 0.0),
        )
        return tuple(x.at[i].set(v) for x, v in zip(tables, (t_left, t_right, ~bad & (t_left <= t_right))))

    zeros = jnp.zeros(lines[0].shape, jnp.float32)
    tables = lax.fori_loop(0, jnp.max(count), interval, (zeros, zeros, jnp.zeros(zeros.shape, bool)))
    return _ObstacleLP(*lines, count, *tables)


def _obstacle_walk(obst: _ObstacleLP, radius, optx, opty, direction_opt):
    """linearProgram2 over the obstacle lines alone (they come first): the result after them (complex) and
    the row where linearProgram1 failed (count: none; the result then stays, as in RVO2)."""
    rx, ry = _lp2_start(radius, optx, opty, direction_opt)

    def step(i, state):
        rx, ry, fail = state
        (pix, piy, dix, diy), (t_left, t_right, ok) = obst.line(i), obst.interval(i)
        hit = (i < obst.count) & (fail == obst.count) & (_det(dix, diy, pix - rx, piy - ry) > 0.0)
        t = _lp1_optimum(optx, opty, pix, piy, dix, diy, t_left, t_right, direction_opt)
        take = hit & ok
        rx, ry = jnp.where(take, pix + t * dix, rx), jnp.where(take, piy + t * diy, ry)
        return rx, ry, jnp.where(hit & ~ok, i, fail)

    rx, ry, fail = lax.fori_loop(0, jnp.max(obst.count), step, (rx, ry, obst.count))
    return lax.complex(rx, ry), fail


def _obstacle_bounds(obst: _ObstacleLP, lines):
    """The interval (t_left, t_right, bad), each (L, P), that the obstacle lines leave on every line of
    ``lines`` (4 x (L, P)), for :func:`linear_program._lp1_bounds`."""
    px = lines[0]
    init = (
        jnp.full(px.shape, -jnp.inf, jnp.float32),
        jnp.full(px.shape, jnp.inf, jnp.float32),
        jnp.zeros(px.shape, bool),
    )

    def step(j, bounds):
        pj = (x[None] for x in obst.line(j))
        return _interval_update(bounds, *lines, *pj, (j < obst.count)[None])

    return lax.fori_loop(0, jnp.max(obst.count), step, init)


def _lp3_obstacle_part(obst: _ObstacleLP, radius, r, fail_o):
    """linearProgram3's loop over the obstacle lines where linearProgram2 failed on one (row fail_o < count):
    from that line on, each obstacle line penetrated deeper than the current worst is minimised subject to
    the obstacle lines (the projected lines are just those).  Returns the result and the worst penetration
    (0 elsewhere), from which the loop goes on over the agent lines."""

    def step(i, state):
        r, distance = state
        pix, piy, dix, diy = obst.line(i)
        hit = (i >= fail_o) & (i < obst.count) & (_det(dix, diy, pix - jnp.real(r), piy - jnp.imag(r)) > distance)
        s, fail = _obstacle_walk(obst, radius, -diy, dix, True)
        r = jnp.where(hit & (fail == obst.count), s, r)
        return r, jnp.where(hit, _det(dix, diy, pix - jnp.real(r), piy - jnp.imag(r)), distance)

    n_rounds = jnp.max(jnp.where(fail_o < obst.count, obst.count, 0))
    return lax.fori_loop(0, n_rounds, step, (r, jnp.zeros(r.shape, jnp.float32)))

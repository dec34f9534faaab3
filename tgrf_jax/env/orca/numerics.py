"""Numeric helpers shared by the solver's modules: RVO2's constants and Vector2 algebra on split x/y arrays, and
the controls over XLA:CPU's fusion that keep each expensive chain one vectorised loop (docs/design.md)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

RVO_EPSILON = 1e-5  # RVO2's RVO_EPSILON (Definitions.h): parallel-line threshold in the LPs.
_BIG = 1e30  # distance key of non-neighbours when ranking (finite, unlike inf)


def _det(ax, ay, bx, by):
    """RVO2 det(a, b) = a.x * b.y - a.y * b.x (cross product z)."""
    return ax * by - ay * bx


def _safe_inv(x):
    """1/x, with 1 where x == 0 (the caller masks those lanes out)."""
    return 1.0 / jnp.where(x == 0.0, 1.0, x)


def _safe_sqrt(x):
    """sqrt clamped at 0, with a gradient that stays finite at 0."""
    pos = x > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _left_of(ax, ay, bx, by, cx, cy):
    """RVO2 leftOf(a, b, c) = det(a - c, b - a): positive where c lies left of the line a -> b."""
    return _det(ax - cx, ay - cy, bx - ax, by - ay)


def _normalized(x, y):
    """RVO2 normalize(v) = v * (1 / abs(v)); (0, 0) for a zero vector (RVO2: NaN)."""
    inv = _safe_inv(_safe_sqrt(x * x + y * y))
    return x * inv, y * inv


def _computed_once(fn, *args):
    """fn(*args) (one array, or a pair of float32 arrays of one shape), computed in one vectorised loop and
    materialised.

    XLA:CPU fuses a cheap elementwise chain into each of its consumers (recomputing it), and gives every output
    of a computation its own loop (recomputing the shared chain in each).  Here the chain is the branch of a
    conditional whose predicate is only known at run time (always true), so it is one fusion whose result is
    materialised; a pair leaves it as one complex64, which the simplifier cannot split into two chains again
    through the conditional.  (A gather with a run-time index would also be a boundary, but XLA fuses the
    chain into the gather, whose loop is not vectorised.)  Elsewhere fusion follows other rules, and a
    conditional waits for its predicate to reach the host: there this is plain fn(*args).
    """
    if jax.default_backend() != "cpu":
        return fn(*args)
    args = tuple(jnp.asarray(x) for x in args)
    pair = isinstance(jax.eval_shape(fn, *args), tuple)

    def run(args):
        out = fn(*args)
        return lax.complex(*out) if pair else out

    out_type = jax.eval_shape(run, args)
    probe = next((x for x in args if jnp.issubdtype(x.dtype, jnp.floating)), None)
    if probe is None:  # x == x folds to True for integers, not for floats (NaN)
        probe = lax.bitcast_convert_type(args[0].astype(jnp.int32), jnp.float32)
    probe = probe.reshape(-1)[0]
    always = probe == probe  # True (no NaN here), but not a constant
    out = lax.cond(always, run, lambda _: jnp.zeros(out_type.shape, out_type.dtype), args)
    return (jnp.real(out), jnp.imag(out)) if pair else out


def _componentwise(fn, args, n_out, shape, extra=()):
    """fn(*args) -> n_out float32 arrays of ``shape``, computed two outputs at a time, plus one more output per
    function of ``extra`` (each fn(*args) -> one float32 array of ``shape``).

    XLA:CPU splits a multi-output elementwise computation into many materialised passes (measured ~20x
    slower than one output), while a single output is one fused loop; so each pair of outputs is its own
    :func:`_computed_once` (one loop, the shared intermediates computed once for both).  This also
    materialises every output once: a cheap elementwise chain with several consumers (the neighbour ranks)
    is otherwise fused into, and recomputed by, each of them.
    """
    outputs = [lambda *a, c=c: fn(*a)[c] for c in range(n_out)] + list(extra)
    values = []
    for c in range(0, len(outputs), 2):
        if c + 1 < len(outputs):
            values += _computed_once(lambda *a, c=c: (outputs[c](*a), outputs[c + 1](*a)), *args)
        else:
            values.append(_computed_once(outputs[c], *args))
    return tuple(values)


def _columns(table, cols):
    """table[..., cols] for a (P,) or (L, P) table, gathered element by element so that the result keeps the
    problems as its minor (vectorised) axis: a gather of whole columns is laid out (cols, L) and transposed."""
    if table.ndim == 1:
        return table[cols]
    idx = jnp.broadcast_to(cols[None, :], (table.shape[0], cols.shape[0]))
    return jnp.take_along_axis(table, idx, axis=1, mode="clip")

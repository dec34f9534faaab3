"""The compile counter that the no-recompilation tests rely on (tests/helpers.py)."""

import jax
import jax.numpy as jnp
from helpers import CompileCounter


def test_counter_sees_compilations_and_not_cache_hits():
    """The counter the no-recompilation tests rely on sees a compilation, and not a cache hit."""
    f = jax.jit(lambda x: jnp.sin(x) * 3.0 + 1.0)
    x3, y3, x4 = jnp.zeros(3), jnp.ones(3), jnp.zeros(4)  # made outside: creating arrays compiles too
    with CompileCounter() as first:
        f(x3).block_until_ready()
    with CompileCounter() as again:
        f(y3).block_until_ready()
    with CompileCounter() as new_shape:
        f(x4).block_until_ready()
    assert first.compiles >= 1 and first.traces >= 1
    assert again.compiles == 0 and again.traces == 0
    assert new_shape.compiles >= 1

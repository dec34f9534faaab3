"""A tune's objective: an arithmetic expression over evaluation metrics, parsed without evaluating Python.

Members of a population may train on different rewards, so they are compared by what they do, not by their
returns: the expression is evaluated on the metrics of the same fixed test episodes for every member
(`tgrf_jax.evaluate.EvalResult`). Allowed: numbers, metric names, `+ - * /`, unary minus, parentheses, and
`min(...)`, `max(...)`, `abs(...)`. Rates are fractions in [0, 1] under their short names (`success`,
`collision`, `timeout`, `psc`), so `0.4 * success + 0.3 * spl + 0.3 * psc` weighs like terms.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import math
import operator
from collections.abc import Callable, Mapping

from tgrf_jax.config import ConfigError

__all__ = ["METRICS", "Objective", "parse_objective"]

# Short name -> (field of EvalResult, scale). The scales turn percentages into fractions so the short names share
# one unit; every field of EvalResult is also accepted under its own name, unscaled.
METRICS: dict[str, tuple[str, float]] = {
    "success": ("success_rate", 1.0),
    "collision": ("collision_rate", 1.0),
    "collision_human": ("collision_human_rate", 1.0),
    "collision_obstacle": ("collision_obstacle_rate", 1.0),
    "timeout": ("timeout_rate", 1.0),
    "nav_time": ("nav_time", 1.0),
    "path_length": ("path_length", 1.0),
    "itr": ("itr_future", 0.01),
    "itr_disc": ("itr_disc", 0.01),
    "spl": ("spl", 1.0),
    "psc": ("personal_space_compliance", 0.01),
    "min_dist": ("min_dist_human", 1.0),
    "jerk": ("jerk_mean", 1.0),
    "time_stalled": ("time_stalled", 1.0),
}

_BINARY = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv}
_FUNCTIONS = {"min": min, "max": max, "abs": abs}


def _eval_result_fields() -> tuple[str, ...]:
    from tgrf_jax.evaluate import EvalResult  # evaluate imports jax; the parser is also used by the CLI's checks

    return tuple(f.name for f in dataclasses.fields(EvalResult) if f.name != "n_episodes")


@dataclasses.dataclass(frozen=True)
class Objective:
    """A parsed objective: `text` as given, `metrics` the names it reads, `score(result_dict)` its value.

    A metric that is undefined for a member (`None`/NaN: no successful episode for `nav_time`) makes the score
    -inf, so such a member ranks last rather than poisoning the comparison."""

    text: str
    metrics: tuple[str, ...]
    _fn: Callable[[Mapping[str, float]], float] = dataclasses.field(repr=False, compare=False)

    def score(self, results: Mapping[str, float | None]) -> float:
        values = {}
        for name in self.metrics:
            field, scale = METRICS.get(name, (name, 1.0))
            raw = results.get(field)
            if raw is None or not math.isfinite(float(raw)):
                return -math.inf
            values[name] = float(raw) * scale
        try:
            value = float(self._fn(values))
        except ZeroDivisionError:
            return -math.inf
        return value if math.isfinite(value) else -math.inf


def _compile(node: ast.AST, text: str, names: list[str], allowed: set[str]) -> Callable:
    if isinstance(node, ast.Expression):
        return _compile(node.body, text, names, allowed)
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
        value = float(node.value)
        return lambda env: value
    if isinstance(node, ast.Name):
        if node.id not in allowed:
            close = difflib.get_close_matches(node.id, sorted(allowed), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(
                f"--objective {text!r}: unknown metric {node.id!r}{hint}; metrics: {', '.join(sorted(METRICS))}, "
                "or any field of an evaluation's JSON"
            )
        names.append(node.id)
        key = node.id
        return lambda env: env[key]
    if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
        op, left, right = _BINARY[type(node.op)], *(_compile(n, text, names, allowed) for n in (node.left, node.right))
        return lambda env: op(left(env), right(env))
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        inner = _compile(node.operand, text, names, allowed)
        sign = -1.0 if isinstance(node.op, ast.USub) else 1.0
        return lambda env: sign * inner(env)
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id in _FUNCTIONS
        and not node.keywords
        and node.args
    ):
        fn = _FUNCTIONS[node.func.id]
        if fn is abs and len(node.args) != 1:
            raise ConfigError(f"--objective {text!r}: abs() takes one argument")
        args = [_compile(a, text, names, allowed) for a in node.args]
        return (lambda env: fn(args[0](env))) if fn is abs else (lambda env: fn(a(env) for a in args))
    shown = ast.get_source_segment(text, node) or type(node).__name__
    raise ConfigError(
        f"--objective {text!r}: {shown!r} is not allowed; use numbers, metric names, + - * /, parentheses, "
        "min(), max(), abs()"
    )


def parse_objective(text: str) -> Objective:
    """Parse an objective expression; raises ConfigError on a syntax error or an unknown metric."""
    if not text or not text.strip():
        raise ConfigError("--objective is empty; e.g. --objective 'success - 0.5 * collision'")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as e:
        # the parser reports an expression cut short (a trailing operator) at offset 0
        where = f"at column {e.offset}" if e.offset and e.offset <= len(text.strip()) else "at its end"
        raise ConfigError(f"--objective {text!r}: syntax error {where}: {e.msg}") from None
    names: list[str] = []
    fn = _compile(tree, text.strip(), names, set(METRICS) | set(_eval_result_fields()))
    if not names:
        raise ConfigError(f"--objective {text!r} reads no metric; e.g. 'success - 0.5 * collision'")
    return Objective(text.strip(), tuple(dict.fromkeys(names)), fn)

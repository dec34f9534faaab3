"""Declaring, validating and loading config fields: the machinery behind `tgrf_jax.config`.

A field is declared once with `spec` (static: shapes and code paths) or `traced` (a float32 leaf of a traced
parameter pytree), with its default, allowed range or choices and a doc string. `check_fields` validates an
instance against those declarations, `from_dict` builds one from a (YAML) mapping with clear errors naming the
dotted field, `apply_overrides` applies `--set section.field=value`, and `traced_pytree` derives a pytree class
from the traced fields.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import pathlib
import re
from collections.abc import Mapping
from typing import Any

import numpy as np
import yaml


class ConfigError(ValueError):
    """A configuration value or key is invalid; the message names the field and what is allowed."""


def spec(
    default,
    *,
    low=None,
    high=None,
    low_inclusive=True,
    high_inclusive=True,
    choices=None,
    doc="",
    traced=False,
    whole=False,
):
    """A static dataclass field with its allowed range or choices (`traced=True`: see `traced`; `whole=True`: a count,
    whole numbers only, stored as an int)."""
    return dataclasses.field(
        default=default,
        metadata=dict(
            low=low,
            high=high,
            low_inclusive=low_inclusive,
            high_inclusive=high_inclusive,
            choices=choices,
            doc=doc,
            traced=traced,
            whole=whole,
        ),
    )


def traced(default, **kwargs):
    """A numeric field that becomes a float32 leaf of the traced parameter pytree of its section."""
    return spec(default, traced=True, **kwargs)


def traced_names(cls) -> tuple[str, ...]:
    """The traced fields of a config dataclass, in declaration order."""
    return tuple(f.name for f in dataclasses.fields(cls) if f.metadata.get("traced"))


def traced_pytree(name: str, config_cls, *, first=(), last=(), base=None, module=None, doc=None):
    """A `flax.struct.dataclass` with one array leaf per traced field of `config_cls`, between the extra
    `(name, type)` fields `first` and `last` (a `last` field may be `(name, type, default)`); `base` (a plain
    class) contributes properties and methods."""
    import jax.numpy as jnp
    from flax import struct

    annotations = {f[0]: f[1] for f in first}
    annotations.update({n: jnp.ndarray for n in traced_names(config_cls)})
    annotations.update({f[0]: f[1] for f in last})
    namespace = {"__annotations__": annotations, "__module__": module or __name__, "__qualname__": name, "__doc__": doc}
    namespace.update({f[0]: f[2] for f in last if len(f) == 3})  # (name, type, default)
    return struct.dataclass(type(name, (base,) if base else (), namespace))


def traced_values(config) -> dict:
    """{name: float32 array} of the traced fields of a config instance."""
    import jax.numpy as jnp

    # A config may leave a traced field at None to mean "follow another field" (env.active_humans_*: the capacity);
    # its `resolved(name)` gives the number the pytree carries.
    value = getattr(config, "resolved", None) or (lambda n: getattr(config, n))
    return {n: jnp.asarray(value(n), jnp.float32) for n in traced_names(type(config))}


def describe_allowed(meta: Mapping[str, Any]) -> str:
    if meta.get("choices") is not None:
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    lo, hi = meta.get("low"), meta.get("high")
    parts = []
    if lo is not None:
        parts.append(f"{'>=' if meta['low_inclusive'] else '>'} {lo}")
    if hi is not None:
        parts.append(f"{'<=' if meta['high_inclusive'] else '<'} {hi}")
    return " and ".join(parts) if parts else "any value"


def _show(value, limit: int = 60) -> str:
    """A value as an error message quotes it: a huge one cut short rather than echoed whole."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text):,} characters)"


# PyYAML reads 1e-3 and 1e20 (no dot) as text; that form is taken as the number it means. Other text ("5" quoted,
# "many") is not a number: quoting a value says it is text.
_EXPONENT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def _number_text(value: str, name: str, kind: str) -> float:
    if _looks_numeric(value) and not math.isfinite(float(value)):  # nan, inf: YAML reads them as text
        raise ConfigError(f"{name} = {_show(value)} must be {'a finite number' if kind == 'a number' else kind}")
    if not _EXPONENT.fullmatch(value.strip()):
        raise ConfigError(
            f"{name} = {_show(value)} must be {kind}"
            + (" (it is quoted text; give the number without quotes)" if _looks_numeric(value) else "")
        )
    return float(value)


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _coerce(value, default, name: str):
    """Coerce a loaded value to the type of the field's default, rejecting lossy conversions."""
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no"):
            return value.lower() in ("true", "1", "yes")
        raise ConfigError(f"{name} = {_show(value)} must be a boolean (true/false)")
    if isinstance(default, int):
        if isinstance(value, bool):
            raise ConfigError(f"{name} = {_show(value)} must be an integer")
        if isinstance(value, str):
            value = _number_text(value, name, "an integer")
        if isinstance(value, float):
            if not value.is_integer():
                raise ConfigError(f"{name} = {_show(value)} must be an integer")
            value = int(value)
        if not isinstance(value, int):
            raise ConfigError(f"{name} = {_show(value)} must be an integer")
        return value
    if isinstance(default, float):
        if isinstance(value, bool):
            raise ConfigError(f"{name} = {_show(value)} must be a number")
        if isinstance(value, str):
            return _number_text(value, name, "a number")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{name} = {_show(value)} must be a number") from None
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{name} = {_show(value)} must be a string")
        return value
    return value


def check_fields(obj, prefix: str, names=None) -> None:
    """Check every field of a config dataclass (or those in `names`) against its declared range/choices."""
    for f in dataclasses.fields(obj):
        if names is not None and f.name not in names:
            continue
        value = getattr(obj, f.name)
        name = f"{prefix}.{f.name}" if prefix else f.name
        meta = f.metadata
        if dataclasses.is_dataclass(value) or value is None:  # None: resolved from other fields, checked there
            continue
        if meta.get("choices") is not None:
            if value not in meta["choices"]:
                raise ConfigError(f"{name} = {_show(value)} is not allowed; allowed: {describe_allowed(meta)}")
            continue
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{name} = {_show(value)} must be finite; allowed: {describe_allowed(meta)}")
        lo, hi = meta.get("low"), meta.get("high")
        too_low = lo is not None and (value < lo if meta["low_inclusive"] else value <= lo)
        too_high = hi is not None and (value > hi if meta["high_inclusive"] else value >= hi)
        if too_low or too_high:
            raise ConfigError(f"{name} = {_show(value)} is out of range; allowed: {describe_allowed(meta)}")


def concrete(value, name: str) -> np.ndarray:
    """A parameter leaf as a host array of real numbers; a traced one (inside jit / vmap) cannot be checked.

    Params are built by hand too (`EnvParams.replace(dt="0.1")`): a string, None, a bool or a ragged list would
    otherwise fail deep inside numpy's comparisons with a message naming no field, or (a bool) pass as 0 / 1."""
    import jax

    if isinstance(value, jax.core.Tracer):
        raise TypeError(f"{name} is traced: parameters are checked on concrete values, outside jit / vmap")
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):  # a ragged nested list, an object numpy cannot read
        a = None
    if a is None or a.dtype.kind not in "fiu":
        kind = type(value).__name__ if a is None or a.dtype == object or not a.shape else f"array of {a.dtype}"
        raise ConfigError(
            f"{name} = {_show(value)} ({kind}) must be a number, or an array of numbers for a batch of params"
        )
    return a


def first_where(bad, *values) -> list | None:
    """The elements of `values` (broadcast to `bad`'s shape) at the first position where `bad` holds, else None."""
    bad = np.asarray(bad)
    if not bad.any():
        return None
    index = tuple(np.argwhere(bad)[0])
    return [np.broadcast_to(np.asarray(v), bad.shape)[index] for v in values]


def check_traced(params, config_cls, prefix: str) -> None:
    """Check the concrete leaves of a parameter pytree (`traced_pytree` of `config_cls`, possibly batched: every
    element) against the declared ranges of `config_cls`'s traced fields; the error names the field, the element
    of a batch and the allowed range."""
    for f in dataclasses.fields(config_cls):
        if not f.metadata.get("traced"):
            continue
        name, meta = f"{prefix}.{f.name}", f.metadata
        a = concrete(getattr(params, f.name), name)
        lo, hi = meta.get("low"), meta.get("high")
        bad = ~np.isfinite(a)
        if lo is not None:  # bounds in the leaf's dtype: a float32 leaf holds a config's 0.01 as float32(0.01)
            bad |= a < a.dtype.type(lo) if meta["low_inclusive"] else a <= a.dtype.type(lo)
        if hi is not None:
            bad |= a > a.dtype.type(hi) if meta["high_inclusive"] else a >= a.dtype.type(hi)
        if bad.any():
            index = tuple(int(i) for i in np.argwhere(bad)[0])
            value = a[index]
            where = f"{name}[{', '.join(map(str, index))}]" if index else name
            what = "is out of range" if np.isfinite(value) else "must be finite"
            raise ConfigError(f"{where} = {value!s} {what}; allowed: {describe_allowed(meta)}")  # float32's own digits


def _unknown_key_error(key: str, prefix: str, valid: list[str]) -> ConfigError:
    key = str(key)  # a YAML key may be a number
    name = f"{prefix}.{key}" if prefix else key
    close = difflib.get_close_matches(key, valid, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return ConfigError(f"unknown config key {name!r}{hint}; valid keys: {', '.join(valid)}")


def from_dict(cls, data: Mapping[str, Any] | None, prefix: str = ""):
    """Build a config dataclass from a (possibly nested, possibly partial) mapping, validating keys and types."""
    data = dict(data or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in fields:
            raise _unknown_key_error(key, prefix, list(fields))
        name = f"{prefix}.{key}" if prefix else key
        default = fields[key].default
        if default is dataclasses.MISSING and fields[key].default_factory is not dataclasses.MISSING:
            default = fields[key].default_factory()
        if dataclasses.is_dataclass(default):
            if not isinstance(value, Mapping):
                raise ConfigError(f"{name} must be a mapping of {type(default).__name__} fields")
            kwargs[key] = from_dict(type(default), value, name)
        else:
            kwargs[key] = _coerce(value, default, name)
    try:
        return cls(**kwargs)
    except ConfigError as e:
        if prefix and not str(e).startswith(prefix):
            raise ConfigError(f"{prefix}.{e}") from None
        raise


def to_dict(obj) -> dict:
    return dataclasses.asdict(obj)


class _UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader that rejects a key given twice in one mapping (plain YAML keeps the last one silently)."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping",
                    node.start_mark,
                    f"found duplicate key {key!r} (first given on line {seen[key] + 1})",
                    key_node.start_mark,
                )
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def yaml_reason(e: yaml.YAMLError) -> str:
    """A YAML error as one line: PyYAML's message spans several, with the offending text and a caret."""
    problem = getattr(e, "problem", None)
    if problem is None:
        return " ".join(str(e).split())[:200]
    mark = getattr(e, "problem_mark", None)
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
    return f"{_show_text(problem)}{where}"


def _show_text(text: str, limit: int = 200) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit] + "..."


def load_yaml(path) -> dict:
    path = pathlib.Path(path)
    if path.is_dir():
        raise ConfigError(f"config file {str(path)!r} is a directory, not a YAML file")
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader)
    except UnicodeDecodeError as e:
        raise ConfigError(f"config file {str(path)!r} is not UTF-8 text ({e.reason} at byte {e.start})") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {yaml_reason(e)}") from None
    except RecursionError:
        raise ConfigError(f"config file {str(path)!r} is nested too deeply to be a config") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {str(path)!r} must hold a mapping at the top level")
    return data


def parse_scalar(raw: str):
    """A command-line value as YAML reads it (1 -> int, 1e-3 -> float, true -> bool); unparsable text as is."""
    if not raw.strip():
        return raw
    try:
        return yaml.safe_load(raw)
    except yaml.YAMLError:
        return raw.strip()
    except RecursionError:
        raise ConfigError(f"value {_show(raw)} is nested too deeply to be a config value") from None


def set_dotted(data: dict, dotted: str, value) -> dict:
    """A copy of the nested dict `data` with `section.field` set to `value`."""
    import copy

    data = copy.deepcopy(data)
    keys = dotted.strip().split(".")
    node = data
    for k in keys[:-1]:
        if node.get(k) is None:
            node[k] = {}
        node = node[k]
        if not isinstance(node, dict):
            raise ConfigError(f"{dotted}: {k!r} is not a section")
    node[keys[-1]] = value
    return data


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    """Apply `a.b.c=value` overrides (values parsed as YAML scalars) to a nested dict, returning a copy."""
    import copy

    data = copy.deepcopy(data)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.field=value")
        dotted, raw = item.split("=", 1)
        try:
            value = parse_scalar(raw)
            # YAML drops " # ..." as a comment: "ppo.lr=1 # was 1e-3" would set 1 without a word
            if re.search(r"(^|\s)#", raw) and not (isinstance(value, str) and "#" in value):
                raise ConfigError("the value holds a YAML comment (' #'); give the value alone")
            data = set_dotted(data, dotted, value)
        except ConfigError as e:
            raise ConfigError(f"override {_show(item)}: {e}") from None
    return data

"""From YAML and ``--set`` overrides to a checked :class:`EstimatorConfig`, and back to plain data and a hash.

Unknown keys and wrong types are errors that name the file and the dotted key (``p.yaml: gnc: unknown key
kapa, did you mean 'gnc.kappa'? ...``, ``p.yaml: gnc.kappa: expected a number, got 'abc'``).
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import math
import typing
from pathlib import Path
from typing import Any

import yaml

from batchpose.config.estimator import EstimatorConfig, validate
from batchpose.errors import ConfigError


def _coerce(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        (inner, _) = typing.get_args(tp)
        return tuple(_coerce(v, inner, where) for v in value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def _unknown_keys(at: str, key: str, unknown: list[Any], known: list[str]) -> ConfigError:
    """``AT: unknown key kapa, did you mean 'gnc.kappa'? (expected one of: ...)``; the suggestion (difflib) is
    the key's dotted path, as ``--set`` takes it."""
    hints = []
    for name in unknown:
        close = difflib.get_close_matches(str(name), known, n=1)
        if close:
            path = f"{key}.{close[0]}" if key else close[0]
            hints.append(f"'{path}'" + (f" for {name}" if len(unknown) > 1 else ""))
    hint = f", did you mean {', '.join(hints)}?" if hints else ""
    return ConfigError(
        f"{at}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(str, unknown))}{hint} "
        f"(expected one of: {', '.join(known)})"
    )


def from_dict(cls: type, data: dict | None, where: str = "config", key: str = "") -> Any:
    """Build dataclass ``cls`` from a nested dict; unknown keys and wrong types raise ConfigError.

    Errors read ``WHERE: KEY: ...`` (e.g. ``pipelines/x.yaml: gnc.kappa: expected a number``); ``key`` is the
    dotted path of ``data`` inside the file (empty at the top).
    """
    data = data or {}
    at = f"{where}: {key}" if key else where
    if not isinstance(data, dict):
        raise ConfigError(f"{at}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields), key=str)
    if unknown:
        raise _unknown_keys(at, key, unknown, list(fields))
    kwargs = {}
    for name, value in data.items():
        tp = hints[name]
        sub = f"{key}.{name}" if key else name
        if dataclasses.is_dataclass(tp):
            kwargs[name] = from_dict(typing.cast(type, tp), value, where, sub)
        else:
            kwargs[name] = _coerce(value, tp, f"{where}: {sub}")
    obj = cls(**kwargs)
    return obj


def to_dict(conf: Any) -> dict:
    """Plain nested dict (tuples as lists) for YAML/JSON output and hashing."""
    out = dataclasses.asdict(conf)

    def fix(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: fix(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [fix(x) for x in v]
        return v

    return fix(out)


def config_hash(*parts: Any) -> str:
    """Stable short hash of config sections / plain values (for cache keys)."""
    blob = json.dumps([to_dict(p) if dataclasses.is_dataclass(p) else p for p in parts], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    """Apply ``a.b=value`` overrides (value parsed as YAML) to a nested dict, returning a new dict."""
    data = json.loads(json.dumps(data))  # deep copy of plain data
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. gnc.kappa=3")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as e:
            raise ConfigError(f"--set {item!r}: cannot parse value: {e}") from None
        node = data
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"--set {item!r}: the key before '=' is empty or has an empty part, e.g. gnc.kappa=3")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {p} is not a section")
        node[parts[-1]] = value
    return data


def load_yaml(path: Path) -> dict:
    """Read a YAML mapping; missing file or bad YAML raise ConfigError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text (byte {e.object[e.start]:#04x} at offset {e.start})") from None
    except yaml.YAMLError as e:
        msg = str(e).replace("\n", " ")
        raise ConfigError(f"{path}: not valid YAML: {msg}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def load_estimator_config(data: dict, where: str = "pipeline") -> EstimatorConfig:
    """The checked config a pipeline dict (a YAML's, after ``--set`` overrides) describes; errors name ``where``."""
    return validate(from_dict(EstimatorConfig, data, where), where)

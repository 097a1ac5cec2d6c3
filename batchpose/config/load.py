"""From YAML and ``--set`` overrides to a checked :class:`EstimatorConfig`, and back to plain data and a hash.

Unknown keys and wrong types are errors that name the file and the dotted key (``p.yaml: gnc: unknown key
kapa, did you mean 'gnc.kappa'? ...``, ``p.yaml: gnc.kappa: expected a number, got 'abc'``); a bad ``--set`` is
blamed on ``--set`` (``--set gnc.kapa=3: unknown key gnc.kapa; did you mean gnc.kappa?``).
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
from batchpose.config.rules import field_problem
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


def _dotted_keys(cls: type, prefix: str = "") -> list[str]:
    """Every dotted key of dataclass ``cls``: its sections and, inside them, their fields (``gnc``, ``gnc.kappa``)."""
    keys = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        keys.append(f"{prefix}{f.name}")
        if dataclasses.is_dataclass(hints[f.name]):
            keys += _dotted_keys(typing.cast(type, hints[f.name]), f"{prefix}{f.name}.")
    return keys


def _unknown_override(item: str, key: str, schema: type, section: type, at: str) -> ConfigError:
    """``--set gnc.kapa=3: unknown key gnc.kapa; did you mean gnc.kappa?``: the keys with the same last part
    (``kappa=3``), else the nearest dotted key (difflib); when none is close, the keys of the section it
    stopped in."""
    keys = _dotted_keys(schema)
    leaf = key.rsplit(".", 1)[-1]
    close = [k for k in keys if k.rsplit(".", 1)[-1] == leaf][:3] or difflib.get_close_matches(
        key, keys, n=1, cutoff=0.75
    )
    if close:
        return ConfigError(f"--set {item}: unknown key {key}; did you mean {' or '.join(close)}?")
    known = ", ".join(f.name for f in dataclasses.fields(section))
    where = f"keys of {at}" if at else "top-level keys and sections"
    return ConfigError(f"--set {item}: unknown key {key} ({where}: {known})")


def _check_override(item: str, parts: list[str], value: Any, schema: type) -> None:
    """Check one ``--set`` against ``schema`` before it is merged: the dotted key exists, the value has the
    field's type and meets its own rules. Errors name ``--set ITEM``, not the pipeline file (rules that tie two
    fields together are checked with the whole config)."""
    key = ".".join(parts)
    cls: Any = schema
    for i, part in enumerate(parts):
        at = ".".join(parts[:i])
        if not dataclasses.is_dataclass(cls):
            raise ConfigError(f"--set {item}: {at} is a value, not a section (e.g. --set {at}=...)")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        if part not in fields:
            raise _unknown_override(item, key, schema, typing.cast(type, cls), at)
        field, cls = fields[part], typing.get_type_hints(cls)[part]
    if dataclasses.is_dataclass(cls):
        from_dict(typing.cast(type, cls), value, f"--set {item}", key)
        return
    problem = field_problem(key, _coerce(value, cls, f"--set {item}"), dict(field.metadata))
    if problem:
        raise ConfigError(f"--set {item}: {problem}")


def apply_overrides(data: dict, overrides: list[str], schema: type = EstimatorConfig) -> dict:
    """Apply ``a.b=value`` overrides (value parsed as YAML) to a nested dict, returning a new dict.

    Each override is checked against dataclass ``schema`` first (the key exists, the value fits the field), so
    a mistake is blamed on ``--set``, with the nearest key: ``--set gnc.kapa=3: unknown key gnc.kapa; did you
    mean gnc.kappa?``.
    """
    data = json.loads(json.dumps(data))  # deep copy of plain data
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item}: expected KEY=VALUE, e.g. gnc.kappa=3")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as e:
            msg = str(e).replace("\n", " ")
            raise ConfigError(f"--set {item}: cannot parse value: {msg}") from None
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"--set {item}: the key before '=' is empty or has an empty part, e.g. gnc.kappa=3")
        _check_override(item, parts, value, schema)
        node = data
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item}: {p} is not a section")
        node[parts[-1]] = value
    return data


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, except that a key given twice in one mapping is an error (PyYAML keeps the last
    one silently, so an edit to the first would do nothing)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: set = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if key in seen:
                line = key_node.start_mark.line + 1
                raise yaml.constructor.ConstructorError(None, None, f"key {key!r} given twice (line {line})")
            seen.add(key)
        return super().construct_mapping(node, deep)


def load_yaml(path: Path) -> dict:
    """Read a YAML mapping; missing file, bad YAML or a key given twice raise ConfigError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: file not found")
    try:
        data = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
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

"""One place per config field: :func:`knob` puts a field's choices and bounds next to its type and default,
and :func:`check_fields` is the one validator that walks the config dataclasses and checks them.

A field reads ``kappa: float = knob(5.0, gt=0)``, its docstring right under it. The rules live in the
field's ``metadata`` (``dataclasses.fields(GncConfig)``), which takes no part in the dataclass's equality,
hash or ``asdict``: the resolved config and its hash are what the plain default gave.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, TypeVar

from batchpose.errors import ConfigError

_T = TypeVar("_T")

RULE_KEYS = ("choices", "ge", "gt", "le", "lt", "off", "nonempty", "note", "subject")


def knob(
    default: _T,
    *,
    choices: Sequence[str] | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    off: str | None = None,
    nonempty: bool = False,
    note: str | None = None,
    subject: str | None = None,
) -> _T:
    """A dataclass field with default ``default`` whose value must meet the given rules.

    Args:
        default: the field's default (immutable: a number, string, bool or tuple).
        choices: the allowed values of a string field, in the order the error message lists them.
        ge, gt, le, lt: bounds (``>=``, ``>``, ``<=``, ``<``); on a tuple field they bound every item.
        off: 0 is allowed too, whatever the bounds, and means this ("full resolution": "0 (full
            resolution) or >= 160").
        nonempty: a tuple field needs at least one item.
        note: why the bound is what it is, shown after it in the error (">= 4 (PnP)").
        subject: the error's subject instead of the field's dotted key (kept where tests match older wording).

    Returns:
        A ``dataclasses.field``, typed as the default so that type checkers see a default value.
    """
    rules = {
        "choices": tuple(choices) if choices is not None else None,
        "ge": ge,
        "gt": gt,
        "le": le,
        "lt": lt,
        "off": off,
        "nonempty": nonempty or None,
        "note": note,
        "subject": subject,
    }
    metadata = {k: v for k, v in rules.items() if v is not None}
    return dataclasses.field(default=default, metadata=metadata)


def rule_text(rules: dict[str, Any], is_list: bool = False) -> str:
    """What a value must be, in words: "in (0, 1]", ">= 6 (PnP)", "0 (off) or positive", "positive", ...."""
    lo, lo_open = (rules["gt"], True) if "gt" in rules else (rules.get("ge"), False)
    hi, hi_open = (rules["lt"], True) if "lt" in rules else (rules.get("le"), False)
    if lo is not None and hi is not None:
        text = f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    elif lo is not None:
        text = "positive" if lo_open and lo == 0 else f"{'>' if lo_open else '>='} {lo:g}"
    elif hi is not None:
        text = f"{'<' if hi_open else '<='} {hi:g}"
    else:
        text = "anything"
    if "note" in rules:
        text += f" ({rules['note']})"
    if is_list:
        items = "positive values" if text == "positive" else f"values {text}"
        text = f"a {'non-empty ' if rules.get('nonempty') else ''}list of {items}"
    if "off" in rules:
        text = f"0 ({rules['off']}) or {text}"
    return text


def _within(value: Any, rules: dict[str, Any]) -> bool:
    if "ge" in rules and not value >= rules["ge"]:
        return False
    if "gt" in rules and not value > rules["gt"]:
        return False
    if "le" in rules and not value <= rules["le"]:
        return False
    return not ("lt" in rules and not value < rules["lt"])


def field_problem(key: str, value: Any, rules: dict[str, Any]) -> str | None:
    """The error (without its file) if ``value`` breaks the field's ``rules``, else None."""
    if "choices" in rules:
        if value not in rules["choices"]:
            return f"{key} = {value!r}, expected one of {', '.join(rules['choices'])}"
        return None
    bounds: dict[str, Any] = {k: rules[k] for k in ("ge", "gt", "le", "lt") if k in rules}
    if not bounds and "nonempty" not in rules:
        return None
    is_list = isinstance(value, tuple)
    if is_list:
        ok = (bool(value) or "nonempty" not in rules) and all(_within(x, bounds) for x in value)
    else:
        ok = ("off" in rules and value == 0) or _within(value, bounds)
    if ok:
        return None
    shown = list(value) if is_list else value
    return f"{rules.get('subject', key)} must be {rule_text(rules, is_list)}, got {shown}"


def check_fields(conf: Any, where: str, prefix: str = "") -> None:
    """Check every field of dataclass ``conf`` (and of its nested sections, in field order) against its
    :func:`knob` rules; raise ConfigError ``WHERE: KEY ...`` for the first that breaks them."""
    for f in dataclasses.fields(conf):
        value = getattr(conf, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            check_fields(value, where, f"{key}.")
            continue
        problem = field_problem(key, value, dict(f.metadata))
        if problem:
            raise ConfigError(f"{where}: {problem}")

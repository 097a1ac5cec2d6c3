"""The pipelines and the Foxglove layout that ship with batchpose, found the same way in a checkout and in an
installed wheel.

In the repository they live at the top (``pipelines/*.yaml``, ``foxglove/layout.json``); ``batchpose/pipelines``
and ``batchpose/foxglove`` are symlinks to them, and the wheel holds them as package data under those names
(``pyproject.toml``). :func:`resolve` turns ``--pipeline NAME|PATH`` into a file; :func:`available` lists the
names with the one-line description each YAML opens with (its first comment line).
"""

from __future__ import annotations

import difflib
from pathlib import Path

from batchpose.errors import ConfigError

#: The pipeline ``batchpose run`` uses when none is given.
DEFAULT = "gnc_pose"

_PACKAGE = Path(__file__).resolve().parents[1]
_SUFFIXES = (".yaml", ".yml")


def pipelines_dir() -> Path:
    """The folder of the bundled pipeline YAMLs (``pipelines/`` of the checkout, or of the installed package)."""
    return (_PACKAGE / "pipelines").resolve()


def layout_template() -> Path:
    """The Foxglove layout template (``foxglove/layout.json`` of the checkout, or of the installed package)."""
    path = (_PACKAGE / "foxglove" / "layout.json").resolve()
    if not path.is_file():  # a broken install, not the user's input
        raise FileNotFoundError(f"{path}: batchpose's Foxglove layout template is missing; reinstall batchpose")
    return path


def _description(path: Path) -> str:
    """The YAML's first comment line (before any key), without ``#``; "" if it opens with no comment."""
    for line in path.read_text(encoding="utf-8").splitlines():
        text = line.strip()
        if not text:
            continue
        if not text.startswith("#"):
            return ""
        return text.lstrip("#").strip()
    return ""


def _bundled() -> dict[str, Path]:
    """Bundled pipeline name -> its YAML, sorted by name."""
    found = sorted(p for p in pipelines_dir().iterdir() if p.suffix in _SUFFIXES and p.is_file())
    return {p.stem: p for p in found}


def available() -> dict[str, str]:
    """Bundled pipeline name -> its one-line description (the YAML's first comment line), sorted by name."""
    return {name: _description(path) for name, path in _bundled().items()}


def _looks_like_path(text: str) -> bool:
    return "/" in text or "\\" in text or text.endswith(_SUFFIXES) or text.startswith(("~", "."))


def resolve(name_or_path: str | Path) -> Path:
    """The pipeline YAML that ``--pipeline`` names.

    Args:
        name_or_path: a bundled pipeline's name (``gnc_pose``, see :func:`available`) or the path of a YAML.

    Returns:
        The path as given when it names an existing file; for a name, the bundled YAML (an absolute path).

    Raises:
        ConfigError: no such file, or an unknown name (with the nearest names and the list).
    """
    text = str(name_or_path).strip()
    given = Path(text).expanduser()
    if text and given.is_file():
        return given
    bundled = _bundled()
    # "fast.yaml" with no such file here is the bundled fast.
    stem = given.stem if given.suffix in _SUFFIXES and given.parent == Path(".") else text
    if stem in bundled:
        return bundled[stem]
    listed = ", ".join(bundled)
    if isinstance(name_or_path, Path) or _looks_like_path(text):
        raise ConfigError(f"{text}: file not found (or give a bundled pipeline by name: {listed})")
    # The nearest names, or at least the nearest one: a name is one of a short list.
    close = difflib.get_close_matches(text, list(bundled), n=3, cutoff=0.5)
    close = close or difflib.get_close_matches(text, list(bundled), n=1, cutoff=0.0)
    hint = f"; did you mean {' or '.join(close)}?" if close else ""
    raise ConfigError(
        f"pipeline {text!r}: no bundled pipeline of that name{hint} (bundled: {listed}; or give a YAML path)"
    )

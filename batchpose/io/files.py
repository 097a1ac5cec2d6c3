"""Files written so that a killed run never leaves one a rerun would trust, and read with one-line errors.

Every artifact is written to ``<name>.tmp`` beside its final path and renamed over it when complete
(:func:`atomic_path`); a rename within a folder is atomic, so a reader sees the old file or the new one.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pandas as pd

from batchpose.errors import DataError


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield ``<path>.tmp`` to write; when the block ends normally it replaces ``path``, when it raises
    (or the process is stopped) the temporary file is removed and ``path`` is untouched."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path: Path, text: str, encoding: str | None = "utf-8") -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding=encoding)
    return Path(path)


def write_bytes_atomic(path: Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_json_atomic(path: Path, obj: Any) -> Path:
    return write_text_atomic(path, json.dumps(obj))


def write_parquet_atomic(df: pd.DataFrame, path: Path) -> Path:
    with atomic_path(path) as tmp:
        df.to_parquet(tmp, index=False)
    return Path(path)


def one_line(e: BaseException) -> str:
    """An exception's text on one line (YAML and MATLAB errors span several)."""
    return " ".join(str(e).split()) or type(e).__name__


def read_text(path: Path) -> str:
    """A text file's contents.

    Raises:
        DataError: the file cannot be read or is not UTF-8 text (naming the file and the first bad byte).
    """
    try:
        return Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise DataError(
            f"{path}: not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset {e.start}); save it as UTF-8"
        ) from None
    except OSError as e:
        raise DataError(f"{path}: cannot read ({e.strerror or e})") from None

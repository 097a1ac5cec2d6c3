"""Open the frames a manifest names: the ``frames:`` mapping's format and keys, and which frames a run uses.

Which frames a run uses: the ``frames:`` keys :data:`SELECT_KEYS` (any format) narrow the source down
(:class:`Selection`, :class:`SelectedFrames`): ``from_s`` / ``to_s`` (logs only) keep the frames logged
that many seconds after the log's start, ``frame_ids`` the listed frames, ``every: N`` every N-th of the
remaining frames (the first, the N+1-th, ...).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from batchpose.core.frames import Frame, FrameSource
from batchpose.errors import ConfigError, DataError
from batchpose.io.folders import BopFrameSource, ImagesFrameSource, YcbvFrameSource

#: Keys allowed in a manifest's ``frames:`` mapping, per format (first tuple: required).
SPEC_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "ycbv": (("format", "root"), ()),
    "bop": (("format", "root"), ("obj_names",)),
    "images": (("format", "root"), ("intrinsics",)),
    "mcap": (("format", "path"), ("image_topic", "calibration_topic", "depth_topic", "rectified")),
}


#: Optional ``frames:`` keys of every format that choose which frames a run uses (:class:`Selection`).
SELECT_KEYS = ("every", "frame_ids", "from_s", "to_s")


def open_frames(spec: Mapping[str, Any], base_dir: Path) -> FrameSource:
    """Open the frame source described by a manifest's ``frames:`` mapping.

    Args:
        spec: ``{format: ycbv, root: PATH}``, ``{format: bop, root: PATH, obj_names: {1: name}}``,
            ``{format: images, root: PATH, intrinsics: PATH}`` (intrinsics default: the first of
            :data:`batchpose.io.folders.INTRINSICS_NAMES` in ROOT: ``intrinsics.yaml``, ``ost.yaml``, ...)
            or ``{format: mcap, path: PATH, image_topic: TOPIC, calibration_topic: TOPIC, depth_topic: TOPIC,
            rectified: BOOL}``
            (topics optional; no depth topic: no depth).
        base_dir: folder that relative paths are resolved against (the manifest's folder).

    Raises:
        ConfigError: unknown format, missing or unknown key.
        DataError: a path does not exist or the data set is malformed.
    """
    if not isinstance(spec, Mapping):
        raise ConfigError(f"frames: expected a mapping with a 'format' key, got {type(spec).__name__}")
    fmt = spec.get("format")
    if fmt not in SPEC_KEYS:
        raise ConfigError(f"frames.format: unknown format {fmt!r} (expected one of {', '.join(SPEC_KEYS)})")
    required, optional = SPEC_KEYS[fmt]
    optional = optional + SELECT_KEYS
    unknown = sorted(set(spec) - set(required) - set(optional))
    if unknown:
        raise ConfigError(
            f"frames.{unknown[0]}: unknown key for format {fmt} (allowed: {', '.join(required + optional)})"
        )
    missing = [k for k in required if spec.get(k) in (None, "")]
    if missing:
        raise ConfigError(f"frames.{missing[0]}: missing (format {fmt} needs {', '.join(required[1:])})")

    def resolve(key: str) -> Path:
        p = Path(str(spec[key])).expanduser()
        p = p if p.is_absolute() else Path(base_dir) / p
        if not p.exists():
            raise DataError(f"frames.{key}: {p} does not exist")
        return p

    selection = Selection.of(spec)
    if fmt == "ycbv":
        source: FrameSource = YcbvFrameSource(resolve("root"))
    elif fmt == "bop":
        names = spec.get("obj_names") or {}
        if not isinstance(names, Mapping):
            raise ConfigError("frames.obj_names: expected a mapping {obj_id: name}")
        source = BopFrameSource(resolve("root"), obj_names=names)
    elif fmt == "images":
        source = ImagesFrameSource(resolve("root"), resolve("intrinsics") if spec.get("intrinsics") else None)
    else:
        from batchpose.io.mcap_read import McapFrameSource  # only io/mcap_* import mcap

        for key in ("image_topic", "calibration_topic", "depth_topic"):
            if spec.get(key) is not None and not isinstance(spec[key], str):
                raise ConfigError(f"frames.{key}: expected a topic name string, got {spec[key]!r}")
        if spec.get("rectified") is not None and not isinstance(spec["rectified"], bool):
            raise ConfigError(f"frames.rectified: expected true or false, got {spec['rectified']!r}")
        source = McapFrameSource(
            resolve("path"),
            image_topic=spec.get("image_topic"),
            calibration_topic=spec.get("calibration_topic"),
            depth_topic=spec.get("depth_topic"),
            rectified=spec.get("rectified"),
        )
    return source if selection is None else SelectedFrames(source, selection)


@dataclasses.dataclass(frozen=True)
class Selection:
    """Which frames of a source a run uses: a manifest's ``frames:`` keys :data:`SELECT_KEYS`.

    Attributes:
        every: keep every ``every``-th frame (the first, then ``every`` frames on), counted among the
            frames the other keys keep.
        frame_ids: keep only these frames (``frame_id`` as in ``poses.csv``); empty: all.
        from_s, to_s: keep the frames logged at least ``from_s`` and less than ``to_s`` seconds after the
            log's start (its first message of any topic, where Foxglove's timeline starts); logs only.
    """

    every: int = 1
    frame_ids: tuple[str, ...] = ()
    from_s: float | None = None
    to_s: float | None = None

    @classmethod
    def of(cls, spec: Mapping[str, Any]) -> Selection | None:
        """The selection a ``frames:`` mapping asks for (None: every frame); one-line ConfigError per bad key."""
        if not any(spec.get(k) is not None for k in SELECT_KEYS):
            return None
        every = spec.get("every", 1)
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ConfigError(f"frames.every: expected a whole number >= 1, got {every!r}")
        ids = spec.get("frame_ids") or ()
        if isinstance(ids, str) or not isinstance(ids, list | tuple) or not all(isinstance(i, str) for i in ids):
            raise ConfigError(f"frames.frame_ids: expected a list of frame ids (strings, as in poses.csv), got {ids!r}")
        bounds = {}
        for key in ("from_s", "to_s"):
            v = spec.get(key)
            if v is None:
                continue
            if spec["format"] != "mcap":
                raise ConfigError(
                    f"frames.{key}: only for format mcap (a {spec['format']} folder has no capture times; "
                    "use frames.frame_ids or frames.every)"
                )
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"frames.{key}: expected seconds after the log's start (a number >= 0), got {v!r}")
            bounds[key] = float(v)
        if "from_s" in bounds and "to_s" in bounds and bounds["to_s"] <= bounds["from_s"]:
            raise ConfigError(f"frames.to_s ({bounds['to_s']:g}) must be after frames.from_s ({bounds['from_s']:g})")
        selection = cls(every=every, frame_ids=tuple(dict.fromkeys(ids)), **bounds)
        return None if selection == cls() else selection

    def describe(self) -> str:
        """E.g. "every 10th frame, from 12 s to 30 s"."""
        parts = []
        if self.every > 1:
            parts.append(f"every {self.every}{_ordinal(self.every)} frame")
        if self.frame_ids:
            parts.append(f"{len(self.frame_ids)} listed frame(s)")
        if self.from_s is not None or self.to_s is not None:
            parts.append(f"from {self.from_s or 0:g} s" + ("" if self.to_s is None else f" to {self.to_s:g} s"))
        return ", ".join(parts)


def _ordinal(n: int) -> str:
    return "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")


class SelectedFrames(FrameSource):
    """The frames of ``source`` a :class:`Selection` keeps, in the source's order.

    Kept frames get ``im_step`` = ``selection.every``, so tracking follows an object from one kept frame to
    the next (within ``track.max_gap_s``). Reading never decodes an image: the frames left out are
    skipped, not decoded, and a log read in time order (an indexed MCAP) is not read past ``to_s``.
    Iterating raises :class:`DataError` at the end when a listed frame id is not in the source.
    """

    def __init__(self, source: FrameSource, selection: Selection) -> None:
        self.source = source
        self.selection = selection
        self._count: int | None = None
        #: after a full pass: first and last image's seconds after the log's start (None before, or no image)
        self.span_s: tuple[float, float] | None = None

    def __iter__(self) -> Iterator[Frame]:
        sel = self.selection
        ids = set(sel.frame_ids)
        seen: set[str] = set()
        timed = sel.from_s is not None or sel.to_s is not None
        start_ns = getattr(self.source, "start_ns", None)
        ordered = getattr(self.source, "time_ordered", False)
        k, first_ns, last_ns = 0, None, None
        for f in self.source:
            start_ns = f.stamp_ns if start_ns is None else start_ns  # no record of the log's start: its first image
            first_ns = f.stamp_ns if first_ns is None else first_ns
            last_ns = f.stamp_ns
            if ids:
                if f.frame_id not in ids:
                    continue
                seen.add(f.frame_id)
            if timed:
                t = (f.stamp_ns - start_ns) * 1e-9
                if sel.to_s is not None and t >= sel.to_s:
                    if ordered:  # nothing later can be in the window: the rest of the log is not read
                        break
                    continue
                if sel.from_s is not None and t < sel.from_s:
                    continue
            k += 1
            if (k - 1) % sel.every == 0:
                yield dataclasses.replace(f, im_step=sel.every) if sel.every > 1 else f
        if first_ns is not None:
            assert start_ns is not None and last_ns is not None  # set with first_ns, by the first frame
            self.span_s = ((first_ns - start_ns) * 1e-9, (last_ns - start_ns) * 1e-9)
        missing = [i for i in sel.frame_ids if i not in seen]
        if missing:
            where = " between frames.from_s and frames.to_s" if timed else ""
            raise DataError(
                f"frames.frame_ids: {len(missing)} listed frame(s) not in {self.source.describe()}{where}, "
                f"e.g. {missing[0]!r}"
            )

    def count(self) -> int:
        """Frames kept: worked out from the source's count when only ``every`` is set, else by reading the
        source once (without decoding an image)."""
        if self._count is None:
            sel = self.selection
            if not sel.frame_ids and sel.from_s is None and sel.to_s is None:
                self._count = math.ceil(self.source.count() / sel.every)
            else:
                self._count = sum(1 for _ in self)
        return self._count

    def obj_id(self, name: str) -> int:
        return self.source.obj_id(name)

    def describe(self) -> str:
        return f"{self.source.describe()}; {self.selection.describe()}"

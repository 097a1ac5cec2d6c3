"""The ``batchpose convert`` command: write a folder data set (YCB-Video, BOP, plain images) as one MCAP log.

The log holds ``/camera/image`` (foxglove.CompressedImage, the PNG/JPEG bytes copied, never
re-encoded), ``/camera/calibration`` (foxglove.CameraCalibration) and, when the data set has ground
truth, ``/ground_truth/poses`` (see :mod:`batchpose.io.mcap_topics`). Reading the log back with
:class:`~batchpose.io.mcap_read.McapFrameSource` gives the same pixels, K and ground truth.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from pathlib import Path

from tqdm import tqdm

from batchpose.core.frames import Frame, FrameSource, image_size
from batchpose.errors import ConfigError, DataError, ImageError
from batchpose.io.mcap_write import write_frames_mcap
from batchpose.io.sources import open_frames

log = logging.getLogger("batchpose")

FORMATS = ("ycbv", "bop", "images")


def checked_frames(frames: Iterable[Frame]) -> Iterator[Frame]:
    """Pass frames through, refusing images that a log must not carry.

    Raises:
        ImageError: an image is empty, has no readable PNG/JPEG header, has zero size, or disagrees
            with the calibration's size (the intrinsics would be wrong for it).
    """
    for frame in frames:
        where = frame.source or frame.frame_id
        if not frame.image_data:
            raise ImageError(f"{where}: image is empty (0 bytes)")
        size = image_size(frame.image_data)
        if size is None:
            raise ImageError(f"{where}: not a readable PNG/JPEG file (cannot read its size from the header)")
        if size[0] == 0 or size[1] == 0:
            raise ImageError(f"{where}: image has zero size {size[0]}x{size[1]}")
        if size != (frame.camera.width, frame.camera.height):
            raise ImageError(
                f"{where}: image is {size[0]}x{size[1]} but its intrinsics are for "
                f"{frame.camera.width}x{frame.camera.height}"
            )
        yield frame


def main(src: Path, out: Path, fmt: str, overwrite: bool = False) -> Path:
    """Convert the data set in ``src`` to the MCAP file ``out`` (written atomically).

    Args:
        src: data set folder (``images``: its intrinsics found as by :class:`batchpose.io.folders.ImagesFrameSource`).
        out: output ``.mcap`` file.
        fmt: layout of ``src``: "ycbv", "bop" or "images".
        overwrite: replace ``out`` if it exists.

    Returns:
        ``out``.

    Raises:
        ConfigError: unknown format, or ``out`` exists without ``overwrite``.
        DataError / ImageError / CameraError: the data set is missing or malformed.
    """
    src, out = Path(src), Path(out)
    if fmt not in FORMATS:
        raise ConfigError(f"convert --format: unknown format {fmt!r} (expected one of {', '.join(FORMATS)})")
    if not src.is_dir():
        raise DataError(f"{src}: data set folder does not exist")
    if out.is_dir():
        raise ConfigError(f"{out}: is a directory; give the path of the .mcap file to write")
    if out.exists() and not overwrite:
        raise ConfigError(f"{out}: already exists (pass --overwrite to replace it)")
    if any(p.exists() and not p.is_dir() for p in out.parents):
        raise ConfigError(f"{out}: a parent of it is a file, not a directory")
    tmp = out.with_name(out.name + ".tmp")  # where the log is written before the rename
    if tmp.exists():
        raise ConfigError(f"{tmp}: already exists (a killed convert's, or yours?); remove or rename it first")
    source: FrameSource = open_frames({"format": fmt, "root": str(src)}, base_dir=Path.cwd())
    out.parent.mkdir(parents=True, exist_ok=True)
    total = source.count()
    frames = tqdm(checked_frames(source), total=total, desc="convert", unit="frame", disable=None)
    n = write_frames_mcap(frames, out, obj_ids=source.obj_id, metadata={"format": fmt, "source": str(src.resolve())})
    log.info(
        "converted %d / %d frames (%s) -> %s (%.1f MB)",
        n,
        total,
        source.describe(),
        out,
        out.stat().st_size / 1e6,
    )
    return out

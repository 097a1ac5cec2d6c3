"""``batchpose init``: a commented data manifest for a log (or an image folder) and a folder of meshes.

The manifest names the topics the reader chooses (:class:`batchpose.io.mcap_read.McapFrameSource`) or the
folder's calibration file explicitly, one object per mesh found (``meshes/NAME.obj|ply|glb|stl`` or
``meshes/NAME/textured.obj``), ``targets: all`` (``annotations`` for data with ground truth), and comments
on each field and the options users most often change. Paths are written relative to the manifest's folder.
The manifest is loaded back (:func:`batchpose.io.manifest.load_manifest`, its frames opened) before it
replaces anything.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from batchpose.errors import BatchposeError, ConfigError, DataError
from batchpose.io.files import atomic_path
from batchpose.io.folders import ImagesFrameSource, folder_format
from batchpose.io.manifest import load_manifest
from batchpose.io.mcap_read import McapFrameSource
from batchpose.io.mcap_topics import IMAGE_SCHEMAS
from batchpose.io.mesh import load_mesh
from batchpose.io.sources import open_frames

logger = logging.getLogger("batchpose")

#: Mesh files taken as objects: ``meshes/NAME<suffix>`` or ``meshes/NAME/textured<suffix>``.
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".stl")


@dataclass(frozen=True)
class FoundMesh:
    """A mesh file found for one object.

    Attributes:
        name: the object's name (the file's stem, or its folder's name).
        path: the mesh file.
        note: what loading it said ("" when it loads as it is): millimetres rescaled, or why a run refuses it.
        usable: False when a run would refuse it (no texture, unreadable).
    """

    name: str
    path: Path
    note: str = ""
    usable: bool = True


def main(
    log: Path,
    meshes: Path,
    out: Path,
    overwrite: bool = False,
    *,
    image_topic: str | None = None,
    calibration_topic: str | None = None,
) -> Path:
    """Write a commented manifest for ``log_path`` and the meshes in ``meshes``.

    Args:
        log: an MCAP log, or a folder of images with its calibration YAML (``ost.yaml``,
            ``intrinsics.yaml``; :data:`batchpose.io.folders.INTRINSICS_NAMES`), or a YCB-Video / BOP folder.
        meshes: a folder of ``NAME.obj|ply|glb|stl`` files or ``NAME/textured.obj`` folders.
        out: the manifest to write (``.yaml``).
        overwrite: replace ``out`` if it exists.
        image_topic, calibration_topic: topics to write instead of the reader's choice (logs only).

    Returns:
        ``out``.

    Raises:
        ConfigError: ``out`` exists (without ``overwrite``) or is a folder; no mesh in ``meshes``; two meshes
            with one name; no mesh a run can use.
        DataError, CameraError: the log or folder cannot be read, or has no image or calibration (naming the
            nearest topic to one named that is not in the log).
    """
    log_path, meshes, out = Path(log), Path(meshes), Path(out)
    if out.is_dir():
        raise ConfigError(f"--out {out}: is a folder; give the manifest's file name, e.g. {log_path.stem}.yaml")
    if out.exists() and not overwrite:
        raise ConfigError(f"--out {out}: already exists; pass --overwrite to replace it")
    if not log_path.exists():
        raise DataError(f"{log_path}: no such file or folder (expected an MCAP log or a folder of images)")
    base = out.resolve().parent
    base.mkdir(parents=True, exist_ok=True)
    frames, has_gt = _frames_block(log_path, base, image_topic, calibration_topic)
    found = find_meshes(meshes)
    objects = _objects_block(found, meshes, base)
    text = "\n".join([_header(log_path, out), f"name: {_q(log_path.stem)}", "", frames, objects, _targets(has_gt)])
    with atomic_path(out) as tmp:
        tmp.write_text(text.rstrip("\n") + "\n", encoding="utf-8")
        _check(tmp)
    logger.debug("wrote %s: %d object(s), frames from %s", out, sum(m.usable for m in found), log)
    return out


def _rel(path: Path, base: Path) -> str:
    """``path`` relative to ``base`` (the manifest's folder), with forward slashes."""
    return Path(os.path.relpath(Path(path).resolve(), base)).as_posix()


def _q(value: str) -> str:
    """A YAML scalar for any string (JSON's double-quoted strings are YAML)."""
    return json.dumps(value)


def _check(path: Path) -> None:
    """Load the written manifest as a run will and open its frames: a manifest init wrote must run."""
    man = load_manifest(path)
    open_frames(man.frames, man.path.parent).count()


def _header(log_path: Path, out: Path) -> str:
    return (
        f"# Data manifest for {log_path.name}, written by `batchpose init`: its frames, objects and meshes.\n"
        f"# Run it:  batchpose run --manifest {out.name} --out runs/{log_path.stem}\n"
        "# Relative paths are relative to this file's folder. Every key: docs/your_data.md and docs/usage.md.\n"
    )


# ------------------------------------------------------------------------------------------------ frames


def _frames_block(
    log_path: Path, base: Path, image_topic: str | None = None, calibration_topic: str | None = None
) -> tuple[str, bool]:
    """The ``frames:`` mapping, commented: the log's topics (or the folder's calibration) and the selection keys;
    and whether the data has ground truth."""
    if log_path.is_dir():
        return _folder_frames(log_path, base)
    src = McapFrameSource(log_path, image_topic=image_topic, calibration_topic=calibration_topic)
    src.first_calibration()  # a calibration a run would refuse fails here, not in the run
    schemas = {sid: sc.name for sid, sc in src.schemas.items()}
    depth = sorted(
        {
            c.topic
            for c in src.channels.values()
            if "depth" in c.topic.lower() and schemas.get(c.schema_id) in IMAGE_SCHEMAS
        }
    )
    lines = [
        "# The frames: an MCAP log. `batchpose inspect LOG` lists its topics.",
        "frames:",
        "  format: mcap",
        f"  path: {_q(_rel(log_path, base))}",
        f"  # The image topic ({src.count()} images). batchpose chose it: the image topic with a calibration",
        "  # beside it, colour before infrared; name another image topic of the log to read that one.",
        f"  image_topic: {_q(src.image_topic)}",
        "  # The camera calibration of those images (sensor_msgs/CameraInfo or foxglove.CameraCalibration):",
        "  # each image uses the latest calibration logged at or before it.",
        f"  calibration_topic: {_q(src.calibration_topic)}",
        "  # Images already undistorted (ROS image_proc's image_rect*): set rectified: true to use the",
        "  # calibration's P instead of K and D (default: true only for an image topic named image_rect*).",
        f"  # rectified: {'true' if src.rectified else 'false'}",
    ]
    if depth:
        lines += [
            "  # Depth registered to the colour images (same camera frame), used by pipelines/rgbd.yaml:",
            f"  # depth_topic: {_q(depth[0])}",
        ]
    lines += _selection_comments(log=True)
    return "\n".join(lines) + "\n", src.gt_topic is not None


def _folder_frames(root: Path, base: Path) -> tuple[str, bool]:
    fmt = folder_format(root)
    if fmt != "images":  # YCB-Video and BOP folders carry their own cameras (and ground truth)
        open_frames({"format": fmt, "root": str(root)}, Path.cwd()).count()
        lines = [
            f"# The frames: a {'YCB-Video' if fmt == 'ycbv' else 'BOP'} folder (cameras per frame from its files).",
            "frames:",
            f"  format: {fmt}",
            f"  root: {_q(_rel(root, base))}",
        ]
    else:
        src = ImagesFrameSource(root)
        lines = [
            f"# The frames: a folder of images ({src.count()}, in file-name order) with one camera calibration.",
            "frames:",
            "  format: images",
            f"  root: {_q(_rel(root, base))}",
            "  # The calibration: batchpose's intrinsics YAML (fx, fy, cx, cy, width, height, dist), the ost.yaml",
            "  # ROS's camera_calibration writes, or OpenCV's calibration YAML.",
            f"  intrinsics: {_q(_rel(src.intrinsics, base))}",
        ]
    has_gt = fmt == "ycbv" or (fmt == "bop" and any([*root.glob("scene_gt.json"), *root.glob("*/scene_gt.json")]))
    return "\n".join(lines + _selection_comments(log=False)) + "\n", has_gt


def _selection_comments(log: bool) -> list[str]:
    lines = [
        "  # Which frames to use (all by default); uncomment to run on part of the data:",
        "  # every: 10              # every 10th frame",
        '  # frame_ids: ["..."]     # only these frames (frame_id as in poses.csv)',
    ]
    if log:
        lines += [
            "  # from_s: 12.0           # from 12 s after the log's start ...",
            "  # to_s: 30.0             # ... to 30 s (Foxglove's timeline)",
        ]
    return lines


# ------------------------------------------------------------------------------------------------ meshes


def find_meshes(meshes: Path) -> list[FoundMesh]:
    """The objects of a mesh folder: one per ``NAME.obj|ply|glb|stl`` or ``NAME/textured.<same>``, by name,
    each loaded once to say whether it is in millimetres (rescaled) or unusable (no texture).

    Raises:
        ConfigError: not a folder, no mesh in it, or two meshes with one name.
    """
    if not meshes.is_dir():
        raise ConfigError(f"--meshes {meshes}: not a folder (expected NAME.obj|ply|glb|stl or NAME/textured.obj)")
    paths: dict[str, Path] = {}
    for p in sorted(meshes.iterdir()):
        if p.is_file() and p.suffix.lower() in MESH_SUFFIXES:
            name, path = p.stem, p
        elif p.is_dir() and any((p / f"textured{s}").is_file() for s in MESH_SUFFIXES):
            name, path = p.name, next(p / f"textured{s}" for s in MESH_SUFFIXES if (p / f"textured{s}").is_file())
        else:
            continue
        if name in paths:
            raise ConfigError(f"--meshes {meshes}: two meshes for object {name!r}: {paths[name]} and {path}")
        paths[name] = path
    if not paths:
        raise ConfigError(
            f"--meshes {meshes}: no mesh (expected NAME.obj, NAME.ply, NAME.glb, NAME.stl or NAME/textured.obj)"
        )
    found = [_load(name, path) for name, path in paths.items()]
    if not any(m.usable for m in found):
        raise ConfigError(f"--meshes {meshes}: no mesh a run can use ({found[0].path}: {found[0].note})")
    return found


def _load(name: str, path: Path) -> FoundMesh:
    try:
        model = load_mesh(path, name=name)
    except BatchposeError as e:
        logger.warning("%s; object %s is left out of the manifest (commented)", e, name)
        return FoundMesh(name, path, str(e).removeprefix(f"{path}: "), usable=False)
    if model.scale != 1.0:
        return FoundMesh(name, path, f"in millimetres (diameter {model.diameter_m * 1000:.0f} mm): rescaled to metres")
    return FoundMesh(name, path)


def _objects_block(found: list[FoundMesh], meshes: Path, base: Path) -> str:
    """``models`` / ``objects``: one template when every mesh follows one layout, else a mesh per object."""
    usable = [m for m in found if m.usable]
    tpls = {"{name}" + m.path.suffix if m.path.parent == meshes else "{name}/" + m.path.name for m in usable}
    lines = [
        "# The objects: one per mesh, named by its file (or folder). A mesh is a textured OBJ (with its .mtl and",
        "# texture image beside it), PLY, GLB or STL (a mesh needs a texture or vertex colours: SIFT matches it).",
        "# Units: metres; a mesh in millimetres (bounding box over 5 units) is found and rescaled, with a warning",
        "# (force it with --set mesh.units=mm or m). Delete an object's line to leave it out.",
    ]
    # evaluation points (ADD, ADD-S against ground truth) where every mesh folder has them, as YCB's do
    points = ', points: "{name}/points.xyz"' if all((m.path.parent / "points.xyz").is_file() for m in usable) else ""
    if len(tpls) == 1:
        lines += [f"models: {{root: {_q(_rel(meshes, base))}, mesh: {_q(tpls.pop())}{points}}}", "objects:"]
        lines += [_object_line(m, f"- {_q(m.name)}") for m in found]
    else:
        lines.append("objects:")
        lines += [_object_line(m, f"{_q(m.name)}: {{mesh: {_q(_rel(m.path, base))}}}") for m in found]
    return "\n".join(lines) + "\n"


def _targets(has_gt: bool) -> str:
    return "\n".join(
        [
            "# Which objects to look for in each frame: all (every object in every frame), or annotations (only",
            "# the objects the ground truth lists in a frame: logs with /ground_truth/poses, YCB-Video, BOP).",
            f"targets: {'annotations' if has_gt else 'all'}",
        ]
    )


def _object_line(m: FoundMesh, entry: str) -> str:
    if not m.usable:
        return f"  # {entry}   # left out: {m.note}"
    return f"  {entry}" + (f"   # {m.note}" if m.note else "")

"""Data manifests (``data_manifest/*.yaml``): which frames, which objects, which meshes.

Example::

    name: ycbv_dev
    frames: {format: ycbv, root: ../../shared/data/ycbv_dev}
    models: {root: ../../shared/data/ycb_models, mesh: "{name}/textured.obj", points: "{name}/points.xyz"}
    objects: [003_cracker_box, 004_sugar_box]
    targets: annotations   # or: all

Relative paths are resolved against the manifest file's folder. ``frames:`` may also choose which frames a
run uses, with ``every``, ``frame_ids`` and (logs) ``from_s`` / ``to_s``: :class:`batchpose.io.sources.Selection`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from batchpose.config import load_yaml
from batchpose.errors import ConfigError

_TOP_KEYS = {"name", "frames", "models", "objects", "targets"}
_MODEL_KEYS = {"root", "mesh", "points"}
_PATH_KEYS = ("root", "path", "intrinsics")


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    mesh: Path
    points: Path | None


@dataclass(frozen=True)
class Manifest:
    """A resolved manifest.

    Attributes:
        name: data set name. path: the manifest file.
        frames: the ``frames:`` mapping with paths made absolute (for :func:`batchpose.io.sources.open_frames`).
        objects: the objects to estimate, with mesh and (optional) evaluation points files.
        targets: "annotations" (objects the ground truth lists in each frame) or "all".
    """

    name: str
    path: Path
    frames: dict
    objects: tuple[ObjectSpec, ...]
    targets: str

    def to_dict(self) -> dict:
        """Plain mapping with absolute paths, to save next to a run."""
        return {
            "name": self.name,
            "frames": self.frames,
            "models": {
                "objects": {
                    o.name: {"mesh": str(o.mesh), "points": str(o.points) if o.points else None} for o in self.objects
                }
            },
            "objects": [o.name for o in self.objects],
            "targets": self.targets,
        }


def _check_template(path: Path, key: str, tpl: str | None) -> None:
    """``models.mesh`` / ``models.points`` may use ``{name}`` (the object's name) and nothing else."""
    if tpl is None:
        return
    try:
        tpl.format(name="x")
    except (KeyError, IndexError, ValueError) as e:
        why = f"unknown field {{{e.args[0]}}}" if isinstance(e, KeyError) else str(e)
        raise ConfigError(f"{path}: models.{key} {tpl!r}: {why} (only {{name}} may be used)") from None


def load_manifest(path: Path) -> Manifest:
    """Read and check a manifest; every problem is a one-line ConfigError naming the file and key."""
    path = Path(path).resolve()
    data = load_yaml(path)
    base = path.parent
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {', '.join(unknown)} (expected: {', '.join(sorted(_TOP_KEYS))})")
    for key in ("frames", "models", "objects"):
        if key not in data:
            raise ConfigError(f"{path}: missing key {key!r}")
    frames = data["frames"]
    if not isinstance(frames, dict) or "format" not in frames:
        raise ConfigError(f"{path}: frames must be a mapping with a format (ycbv, bop, images, mcap)")
    frames = dict(frames)
    for k in _PATH_KEYS:
        if k in frames and isinstance(frames[k], str):
            frames[k] = str((base / frames[k]).resolve())
    models = data["models"]
    if not isinstance(models, dict):
        raise ConfigError(f"{path}: models must be a mapping with root, mesh, points")
    unknown = sorted(set(models) - _MODEL_KEYS)
    if unknown:
        raise ConfigError(f"{path}: models: unknown key(s) {', '.join(unknown)} (expected root, mesh, points)")
    for key in _MODEL_KEYS:
        if key in models and not isinstance(models[key], str):
            raise ConfigError(f"{path}: models.{key} must be a string (a path), got {models[key]!r}")
    root = (base / models.get("root", ".")).resolve()
    mesh_tpl = models.get("mesh", "{name}/textured.obj")
    points_tpl = models.get("points")
    for key, tpl in (("mesh", mesh_tpl), ("points", points_tpl)):
        _check_template(path, key, tpl)
    objects = data["objects"]
    if not isinstance(objects, list) or not objects or not all(isinstance(o, str) for o in objects):
        raise ConfigError(f"{path}: objects must be a non-empty list of object names")
    specs = []
    for name in objects:
        mesh = root / mesh_tpl.format(name=name)
        if not mesh.is_file():
            raise ConfigError(f"{path}: object {name!r} has no mesh at {mesh}")
        pts = root / points_tpl.format(name=name) if points_tpl else None
        if pts is not None and not pts.is_file():
            raise ConfigError(f"{path}: object {name!r}: points file {pts} not found")
        specs.append(ObjectSpec(name, mesh, pts))
    targets = data.get("targets", "annotations")
    if targets not in ("annotations", "all"):
        raise ConfigError(f"{path}: targets = {targets!r}, expected annotations or all")
    return Manifest(str(data.get("name", path.stem)), path, frames, tuple(specs), targets)

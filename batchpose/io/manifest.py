"""Data manifests (``data_manifest/*.yaml``): which frames, which objects, which meshes.

Example::

    name: ycbv_dev
    frames: {format: ycbv, root: ../../shared/data/ycbv_dev}
    models: {root: ../../shared/data/ycb_models, mesh: "{name}/textured.obj", points: "{name}/points.xyz"}
    objects: [003_cracker_box, 004_sugar_box]
    targets: annotations   # or: all; default: annotations where the data set has ground truth, else all

``objects`` may also map each name to its own files and id, without ``models``::

    objects:
      cracker_box: {mesh: meshes/cracker_box.obj, obj_id: 2}
      mustard: {mesh: meshes/mustard/textured.obj, points: meshes/mustard/points.xyz}

(the form a run saves as ``RUN_DIR/manifest.yaml``, so that file can be passed back as ``--manifest``).
Relative paths are resolved against the manifest file's folder. ``frames:`` may also choose which frames a
run uses, with ``every``, ``frame_ids`` and (logs) ``from_s`` / ``to_s``: :class:`batchpose.io.sources.Selection`.
"""

from __future__ import annotations

import difflib
import itertools
from dataclasses import dataclass
from pathlib import Path

from batchpose.config import load_yaml
from batchpose.errors import ConfigError

_TOP_KEYS = {"name", "frames", "models", "objects", "targets"}
_MODEL_KEYS = {"root", "mesh", "points"}
_OBJECT_KEYS = {"mesh", "points", "obj_id"}
#: ``targets:`` values; ``auto`` (the default) is ``annotations`` where the data set has ground truth, else ``all``.
TARGETS = ("annotations", "all", "auto")
_PATH_KEYS = ("root", "path", "intrinsics")


@dataclass(frozen=True)
class ObjectSpec:
    """One object: its name, mesh, optional evaluation points and optional id (``obj_id`` in ``poses.csv``)."""

    name: str
    mesh: Path
    points: Path | None
    obj_id: int | None = None


@dataclass(frozen=True)
class Manifest:
    """A resolved manifest.

    Attributes:
        name: data set name. path: the manifest file.
        frames: the ``frames:`` mapping with paths made absolute (for :func:`batchpose.io.sources.open_frames`).
        objects: the objects to estimate, with mesh and (optional) evaluation points files.
        targets: "annotations" (objects the ground truth lists in each frame), "all", or "auto" (annotations
            where the data set has ground truth, else all: resolved by the run once the frames are indexed).
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
            "objects": {o.name: _object_dict(o) for o in self.objects},
            "targets": self.targets,
        }


def _object_dict(o: ObjectSpec) -> dict:
    out: dict = {"mesh": str(o.mesh)}
    if o.points is not None:
        out["points"] = str(o.points)
    if o.obj_id is not None:
        out["obj_id"] = o.obj_id
    return out


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
    for key in ("frames", "objects"):
        if key not in data:
            raise ConfigError(f"{path}: missing key {key!r}")
    frames = data["frames"]
    if not isinstance(frames, dict) or "format" not in frames:
        raise ConfigError(f"{path}: frames must be a mapping with a format (ycbv, bop, images, mcap)")
    frames = dict(frames)
    for k in _PATH_KEYS:
        if k in frames and isinstance(frames[k], str):
            frames[k] = str((base / frames[k]).resolve())
    specs = _object_specs(path, data)
    targets = data.get("targets", "auto")
    if targets not in TARGETS:
        raise ConfigError(f"{path}: targets = {targets!r}, expected annotations, all or auto")
    return Manifest(str(data.get("name", path.stem)), path, frames, tuple(specs), targets)


def _models(path: Path, data: dict) -> tuple[Path, str | None, str | None]:
    """``models:`` -> (root, mesh template, points template); the mesh template is None without ``models``."""
    models = data.get("models", {})
    if not isinstance(models, dict):
        raise ConfigError(f"{path}: models must be a mapping with root, mesh, points")
    unknown = sorted(set(models) - _MODEL_KEYS)
    if unknown:
        raise ConfigError(f"{path}: models: unknown key(s) {', '.join(unknown)} (expected root, mesh, points)")
    for key in _MODEL_KEYS:
        if key in models and not isinstance(models[key], str):
            raise ConfigError(f"{path}: models.{key} must be a string (a path), got {models[key]!r}")
    root = (path.parent / models.get("root", ".")).resolve()
    mesh_tpl = models.get("mesh", "{name}/textured.obj") if "models" in data else None
    points_tpl = models.get("points")
    for key, tpl in (("mesh", mesh_tpl), ("points", points_tpl)):
        _check_template(path, key, tpl)
    return root, mesh_tpl, points_tpl


def _object_specs(path: Path, data: dict) -> list[ObjectSpec]:
    """``objects:`` as a list of names (files from the ``models`` templates) or a mapping name -> {mesh,
    points, obj_id}; every mesh and points file must exist, ids must be distinct positive integers."""
    objects = data["objects"]
    if isinstance(objects, list) and objects and all(isinstance(o, str) for o in objects):
        objects = {o: {} for o in objects}
    if not isinstance(objects, dict) or not objects or not all(isinstance(v, dict | None) for v in objects.values()):
        raise ConfigError(
            f"{path}: objects must be a non-empty list of object names, or a mapping name -> {{mesh, points, obj_id}}"
        )
    root, mesh_tpl, points_tpl = _models(path, data)
    specs = []
    for name, entry in objects.items():
        entry = entry or {}
        unknown = sorted(set(entry) - _OBJECT_KEYS)
        if unknown:
            raise ConfigError(
                f"{path}: objects.{name}: unknown key(s) {', '.join(unknown)} (expected mesh, points, obj_id)"
            )
        if "mesh" in entry:
            mesh = (path.parent / str(entry["mesh"])).resolve()
        elif mesh_tpl is not None:
            mesh = root / mesh_tpl.format(name=name)
        else:
            raise ConfigError(f"{path}: object {name!r} has no mesh (give objects.{name}.mesh, or models.mesh)")
        if not mesh.is_file():
            raise ConfigError(f"{path}: object {name!r} has no mesh at {mesh}{_did_you_mean(name, root)}")
        pts_name = entry.get("points") or (points_tpl.format(name=name) if points_tpl else None)
        pts = (root if "points" not in entry else path.parent) / pts_name if pts_name else None
        if pts is not None and not pts.is_file():
            raise ConfigError(f"{path}: object {name!r}: points file {pts} not found")
        obj_id = entry.get("obj_id")
        if obj_id is not None and (isinstance(obj_id, bool) or not isinstance(obj_id, int) or obj_id < 1):
            raise ConfigError(f"{path}: objects.{name}.obj_id = {obj_id!r}, expected a positive integer")
        specs.append(ObjectSpec(str(name), mesh, pts.resolve() if pts else None, obj_id))
    ids = [s.obj_id for s in specs if s.obj_id is not None]
    if len(ids) != len(set(ids)):
        raise ConfigError(f"{path}: objects: two objects have the same obj_id ({sorted(ids)})")
    return specs


def _did_you_mean(name: str, root: Path) -> str:
    """``; did you mean X?`` naming the model folder's entry nearest ``name`` (empty when none is close)."""
    try:
        names = [p.stem if p.is_file() else p.name for p in root.iterdir()]
    except OSError:
        return ""
    close = difflib.get_close_matches(name, names, n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def object_ids(objects: tuple[ObjectSpec, ...], known: dict[str, int]) -> dict[str, int]:
    """Each object's id: the manifest's ``obj_id``, else the data set's (``known``: YCB-Video's classes, a
    BOP data set's ids; 0 = none), else the smallest positive id not yet taken, in manifest order."""
    ids = {o.name: o.obj_id for o in objects if o.obj_id is not None}
    for o in objects:
        if o.name not in ids and known.get(o.name, 0) > 0 and known[o.name] not in ids.values():
            ids[o.name] = known[o.name]
    taken = set(ids.values())
    free = (i for i in itertools.count(1) if i not in taken)
    return {o.name: ids[o.name] if o.name in ids else next(free) for o in objects}

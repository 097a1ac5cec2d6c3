"""Load a finished run directory for the report: its tables, objects, config and model points.

Reads the run directory the pipeline writes:
    ``poses.parquet`` (required; :mod:`batchpose.core.poses` format), ``gt.parquet`` (frame_id, obj_name,
    obj_id, R, t_m; absent or empty = no ground truth), ``frames.parquet`` (frame_id, scene_id, im_id,
    stamp_ns, width, height, K, source), ``objects.json`` ({obj_name: {obj_id, mesh, points, diameter_m}}),
    ``config.yaml``, ``versions.json`` and ``manifest.yaml`` (its ``frames:`` spec, for the overlay gallery).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from batchpose.config import MeshConfig, load_estimator_config
from batchpose.errors import BatchposeError, DataError, MeshError

log = logging.getLogger("batchpose")

#: Points sampled from the mesh when an object has no points file (seeded, reproducible).
MESH_SAMPLES = 2000
#: Largest factor by which the diameter of an object's model points (points file, or mesh samples) may differ
#: from the ``diameter_m`` the run measured on its mesh. On the YCB models the points span 0.99-1.0 of it;
#: a unit slip is a factor of 10 (cm) or 1000 (mm), a truncated or foreign points file usually more than 1.5.
DIAMETER_TOLERANCE = 1.5


@dataclass
class RunData:
    """Everything the report reads from one run directory."""

    run_dir: Path
    poses: pd.DataFrame
    gt: pd.DataFrame | None
    frames: pd.DataFrame | None
    objects: dict[str, dict[str, Any]]
    config_text: str = ""
    versions: dict[str, Any] = field(default_factory=dict)
    manifest: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)
    mesh_conf: MeshConfig = field(default_factory=MeshConfig)
    """The run's ``pipeline.mesh`` options (from ``config.yaml``): how its meshes were brought to metres."""
    _models: dict[str, tuple[np.ndarray, float]] = field(default_factory=dict, repr=False)

    @property
    def has_gt(self) -> bool:
        return self.gt is not None and len(self.gt) > 0

    @property
    def n_frames(self) -> int:
        """Frames of the run: rows of ``frames.parquet``, else the frames that have an estimate."""
        return len(self.frames) if self.frames is not None else self.poses["frame_id"].nunique()

    def model_points(self, names: Iterable[str]) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        """:func:`load_model_points` with this run's objects.json and mesh options; each object read once."""
        names = sorted(set(names))
        todo = [n for n in names if n not in self._models]
        if todo:
            where = str(self.run_dir / "objects.json")
            points, diameters = load_model_points(self.objects, todo, where=where, mesh_conf=self.mesh_conf)
            self._models.update({n: (points[n], diameters[n]) for n in todo})
        return {n: self._models[n][0] for n in names}, {n: self._models[n][1] for n in names}


def _read_parquet(path: Path, required: Iterable[str]) -> pd.DataFrame:
    try:
        df = pd.read_parquet(path)
    except (OSError, ValueError) as e:  # pyarrow's errors derive from these
        raise DataError(f"{path}: cannot read Parquet ({e})") from None
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}")
    return df


def load_run(run_dir: Path) -> RunData:
    """Load a run directory (see the module docstring for its layout).

    Raises:
        DataError: ``poses.parquet`` is missing, or a present file is malformed.
    """
    run_dir = Path(run_dir)
    poses_path = run_dir / "poses.parquet"
    if not poses_path.is_file():
        if (run_dir / "config.yaml").is_file():
            raise DataError(
                f"{run_dir}: the run is unfinished (no poses.parquet yet); rerun the same `batchpose run` "
                "command to finish it (finished pairs are kept)"
            )
        raise DataError(f"{run_dir}: no poses.parquet (is this a run directory written by `batchpose run`?)")
    poses = _read_parquet(poses_path, ("frame_id", "obj_name", "status", "R", "t_m", "confidence"))
    gt = None
    if (run_dir / "gt.parquet").is_file():
        gt = _read_parquet(run_dir / "gt.parquet", ("frame_id", "obj_name", "R", "t_m"))
    frames = None
    if (run_dir / "frames.parquet").is_file():
        frames = _read_parquet(run_dir / "frames.parquet", ("frame_id",))
    run = RunData(run_dir=run_dir, poses=poses, gt=gt, frames=frames, objects=_read_objects(run_dir / "objects.json"))
    if (run_dir / "config.yaml").is_file():
        run.config_text = (run_dir / "config.yaml").read_text(errors="replace")
        run.mesh_conf = _mesh_config(run_dir / "config.yaml", run.config_text, run.notes)
    if (run_dir / "versions.json").is_file():
        try:
            run.versions = json.loads((run_dir / "versions.json").read_text())
        except json.JSONDecodeError as e:
            run.notes.append(f"versions.json is not valid JSON ({e})")
    if (run_dir / "manifest.yaml").is_file():
        try:
            run.manifest = yaml.safe_load((run_dir / "manifest.yaml").read_text())
        except yaml.YAMLError as e:
            run.notes.append(f"manifest.yaml is not valid YAML ({e})")
    return run


def _read_objects(path: Path) -> dict[str, dict[str, Any]]:
    """``objects.json`` ({obj_name: {obj_id, mesh, points, diameter_m}}); {} when absent."""
    if not path.is_file():
        return {}
    try:
        objects = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: invalid JSON ({e})") from None
    if not isinstance(objects, dict) or not all(isinstance(v, dict) for v in objects.values()):
        raise DataError(f"{path}: expected {{obj_name: {{obj_id, mesh, points, diameter_m}}}}")
    return objects


def _mesh_config(path: Path, text: str, notes: list[str]) -> MeshConfig:
    """The ``pipeline.mesh`` section of a run's ``config.yaml`` (defaults when the file has none).

    Raises:
        ConfigError: the section is malformed (unknown key, bad value).
    """
    try:
        saved = yaml.safe_load(text)
    except yaml.YAMLError as e:
        msg = str(e).replace("\n", " ")
        notes.append(f"config.yaml is not valid YAML ({msg}); meshes scored with the default mesh options")
        return MeshConfig()
    pipeline = saved.get("pipeline") if isinstance(saved, dict) else None
    section = pipeline.get("mesh") if isinstance(pipeline, dict) else None
    if section is None:
        return MeshConfig()
    return load_estimator_config({"mesh": section}, where=f"{path}: pipeline").mesh


def fetch_frames(run: RunData, frame_ids: set[str]) -> tuple[dict[str, Any], str]:
    """Frames by id from the manifest's ``frames:`` source; ({}, reason) when that is impossible."""
    if not frame_ids:
        return {}, ""
    if run.manifest is None:
        return {}, "the run directory has no readable manifest.yaml to read frames from"
    spec = run.manifest.get("frames") if isinstance(run.manifest, dict) else None
    if spec is None:
        return {}, "manifest.yaml has no 'frames:' entry"
    try:
        from batchpose.io.sources import open_frames

        found: dict[str, Any] = {}
        for frame in open_frames(spec, run.run_dir):
            if frame.frame_id in frame_ids:
                found[frame.frame_id] = frame
                if len(found) == len(frame_ids):
                    break
    except ImportError as e:
        return {}, f"the frame readers are unavailable ({e})"
    except Exception as e:  # noqa: BLE001 - any reader failure costs the gallery, never the report
        msg = str(e) if isinstance(e, BatchposeError) else f"{type(e).__name__}: {e}"
        return {}, f"cannot read frames from the manifest ({msg})"
    missing = len(frame_ids) - len(found)
    note = f"{missing} of {len(frame_ids)} frames were not found in the frame source" if missing else ""
    return found, note


# --------------------------------------------------------------------------------------- model points


def _sample_mesh(mesh_path: Path, mesh_conf: MeshConfig = MeshConfig()) -> np.ndarray:
    """(MESH_SAMPLES, 3) seeded surface samples of a mesh, metres: scaled exactly as the estimator's load_mesh."""
    import trimesh

    from batchpose.io.mesh import unit_scale

    try:
        try:
            mesh = trimesh.load(mesh_path, force="mesh", process=False, skip_materials=True)
        except TypeError:
            mesh = trimesh.load(mesh_path, force="mesh", process=False)
    except (OSError, ValueError, KeyError, IndexError, AttributeError) as e:  # trimesh's loaders vary
        raise MeshError(f"{mesh_path}: cannot load mesh to sample model points ({e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise MeshError(f"{mesh_path}: mesh has no faces to sample model points from")
    scale = unit_scale(mesh_path, mesh.bounds, mesh_conf)
    if scale != 1.0:
        mesh.apply_scale(scale)
    pts, _ = trimesh.sample.sample_surface(mesh, MESH_SAMPLES, seed=0)
    return np.asarray(pts, dtype=np.float64)


def _points_to_metres(pts: np.ndarray, diameter_m: float | None, mesh_conf: MeshConfig, label: str) -> np.ndarray:
    """Scale a points file's (N, 3) coordinates to metres, by agreement with the object's mesh.

    The estimator never reads the points file, so its units are decided against the mesh the estimator used:
    the points are taken as metres when their diameter matches ``diameter_m`` (the run's metre diameter of
    the mesh), as millimetres (scaled by 0.001, the estimator's factor) when it matches 1000 times that, and
    refused otherwise. Without a ``diameter_m`` the mesh rule (:func:`batchpose.io.mesh.unit_scale`) applies to
    the points' own bounding box.

    Raises:
        DataError: the points match neither scale, or are millimetres under ``mesh.on_millimetres: refuse``.
        MeshError: no ``diameter_m`` and the points look like millimetres under ``on_millimetres: refuse``.
    """
    from batchpose.core.model import diameter
    from batchpose.io.mesh import unit_scale

    if diameter_m is None:
        return pts * unit_scale(Path(label), np.stack([pts.min(axis=0), pts.max(axis=0)]), mesh_conf)
    span = diameter(pts)
    scale = next((s for s in (1.0, 0.001) if _agrees(span * s, diameter_m)), None)
    if scale is None:
        raise DataError(
            f"{label}: the points span {span:.4g} units but the object's mesh is {diameter_m:.4g} m across; "
            "they are neither in metres nor in millimetres of that mesh (wrong units or another object)"
        )
    if scale != 1.0:
        if mesh_conf.units == "auto" and mesh_conf.on_millimetres == "refuse":
            raise DataError(
                f"{label}: the points span {span:.1f} units for a {diameter_m:.3f} m object, so they look like "
                "millimetres; convert them to metres or set mesh.on_millimetres: convert"
            )
        log.warning(
            "%s: the points span %.1f units for a %.3f m object, so they look like millimetres; scaling by 0.001",
            label,
            span,
            diameter_m,
        )
    return pts * scale


def _agrees(span_m: float, diameter_m: float) -> bool:
    return diameter_m / DIAMETER_TOLERANCE <= span_m <= diameter_m * DIAMETER_TOLERANCE


def _entry_diameter(entry: Mapping[str, Any], label: str) -> float | None:
    """An objects.json entry's ``diameter_m`` (metres), None when absent or null."""
    diam = entry.get("diameter_m")
    if diam is None:
        return None
    try:
        diam = float(diam)
    except (TypeError, ValueError):
        diam = float("nan")
    if not (np.isfinite(diam) and diam > 0):
        raise DataError(f"{label}.diameter_m: expected a positive number of metres, got {entry.get('diameter_m')!r}")
    return diam


def _read_points_file(path: Path, label: str) -> np.ndarray:
    """(N, 3) coordinates of an xyz text file, in the file's own units."""
    try:
        pts = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as e:
        raise DataError(f"{label}: cannot read {path} ({e})") from None
    if pts.ndim != 2 or pts.shape[1] < 3 or len(pts) == 0:
        raise DataError(f"{label}: {path} must hold x y z per line, got {pts.shape}")
    if not np.all(np.isfinite(pts[:, :3])):
        raise DataError(f"{label}: {path} has NaN or infinite coordinates")
    return pts[:, :3]


def load_model_points(
    objects: Mapping[str, Mapping[str, Any]],
    names: Iterable[str],
    where: str = "objects.json",
    mesh_conf: MeshConfig = MeshConfig(),
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Model points and diameters of the named objects, in metres as the estimator saw the object.

    Points come from each object's ``points`` file (xyz text) or, when it is null, from :data:`MESH_SAMPLES`
    seeded surface samples of its ``mesh``. A mesh is scaled by the estimator's units rule
    (:func:`batchpose.io.mesh.unit_scale` with ``mesh_conf``, the run's ``pipeline.mesh``); a points file is
    taken as metres or millimetres by agreement with the mesh's ``diameter_m`` (see :func:`_points_to_metres`).
    Either way the points must span the object's ``diameter_m`` to within :data:`DIAMETER_TOLERANCE`.

    Returns:
        ``(points, diameters)``: obj_name -> (N, 3) float64 metres; obj_name -> diameter, metres (the
        ``diameter_m`` entry, or the diameter of the points when it is missing).

    Raises:
        DataError: an object is not listed, its points file is unreadable, or its points disagree in scale
            with its mesh. MeshError: unreadable mesh, or a millimetre mesh under ``on_millimetres: refuse``.
    """
    from batchpose.core.model import diameter

    points: dict[str, np.ndarray] = {}
    diameters: dict[str, float] = {}
    for name in sorted(set(names)):
        entry = objects.get(name)
        if entry is None:
            raise DataError(f"{where}: object {name!r} is not listed (needed for its model points)")
        diam = _entry_diameter(entry, f"{where}: {name}")
        if entry.get("points"):
            path = Path(entry["points"])
            pts = _read_points_file(path, f"{where}: {name}.points")
            pts = _points_to_metres(pts, diam, mesh_conf, f"{where}: {name}.points: {path}")
        elif entry.get("mesh"):
            mesh_path = Path(entry["mesh"])
            pts = _sample_mesh(mesh_path, mesh_conf)
            span = diameter(pts)
            if diam is not None and not _agrees(span, diam):
                raise DataError(
                    f"{where}: {name}: the mesh {mesh_path}, scaled by the run's mesh options, spans "
                    f"{span:.4g} m but the run measured it {diam:.4g} m across (mesh changed since the run, or "
                    "different mesh options)"
                )
        else:
            raise DataError(f"{where}: {name}: needs a 'points' file or a 'mesh'")
        points[name] = pts
        if diam is None:
            diam = diameter(pts)
            log.warning("%s: %s has no diameter_m; using %.4f m from its points", where, name, diam)
        diameters[name] = float(diam)
    return points, diameters

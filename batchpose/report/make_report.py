"""Stage: score a finished run and write ``RUN/report/{summary.csv, frames.csv, index.html}``.

Reads the run directory the pipeline writes:
    ``poses.parquet`` (required; :mod:`batchpose.core.poses` format), ``gt.parquet`` (frame_id, obj_name,
    obj_id, R, t_m; absent or empty = no ground truth), ``frames.parquet`` (frame_id, scene_id, im_id,
    stamp_ns, width, height, K, source), ``objects.json`` ({obj_name: {obj_id, mesh, points, diameter_m}}),
    ``config.yaml``, ``versions.json`` and ``manifest.yaml`` (its ``frames:`` spec, for the overlay gallery).

The HTML is self-contained (plots and overlays inline as base64 PNG, no scripts, no external CSS), so it
opens offline from disk. With ground truth it shows the paper-style table beside the paper's reported
numbers, accuracy-threshold curves, error distributions, confidence vs error and overlays of the best and
worst cases; without ground truth, the detection rate, confidence distribution and overlays of estimates.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import json
import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
import yaml

from batchpose.config import MeshConfig, load_estimator_config
from batchpose.core.poses import STAGES, STATUSES, row_cam_from_model
from batchpose.errors import BatchposeError, DataError, MeshError
from batchpose.io.files import write_text_atomic
from batchpose.report import metrics

log = logging.getLogger("batchpose")

#: GNC-Pose's per-object (ADD-S AUC, ADD AUC) as reported in the paper's YCB table (SPEC §7).
PAPER_GNC_POSE: dict[str, tuple[float, float]] = {
    "002_master_chef_can": (92.1, 51.3),
    "003_cracker_box": (75.0, 68.9),
    "004_sugar_box": (69.2, 50.0),
    "005_tomato_soup_can": (93.7, 87.1),
    "006_mustard_bottle": (96.4, 93.6),
    "007_tuna_fish_can": (83.2, 70.4),
    "008_pudding_box": (83.2, 72.8),
    "009_gelatin_box": (86.6, 78.4),
    "010_potted_meat_can": (90.8, 80.7),
    "021_bleach_cleanser": (94.1, 87.3),
    "035_power_drill": (84.2, 61.9),
    "040_large_marker": (80.0, 64.3),
    "mean": (85.7, 72.2),
}
#: Mean (ADD-S AUC, ADD AUC) of every method in the paper's YCB table (SPEC §7).
PAPER_MEANS: dict[str, tuple[float, float]] = {
    "GNC-Pose": (85.7, 72.2),
    "PoseCNN": (80.4, 62.4),
    "LoFTR": (63.3, 36.8),
    "DeepIM": (92.0, 83.9),
    "FoundationPose": (97.8, 91.8),
    "template upper bound": (64.3, 23.1),
}
PAPER_NOTE = (
    "reported by the paper on a different test set (its own 120 random images per object, top-down "
    "views excluded); shown for orientation, not a like-for-like comparison"
)
#: Number of best / worst / failed cases in the overlay gallery.
GALLERY_K = 4
#: Points sampled from the mesh when an object has no points file (seeded, reproducible).
MESH_SAMPLES = 2000
#: Largest factor by which the diameter of an object's model points (points file, or mesh samples) may differ
#: from the ``diameter_m`` the run measured on its mesh. On the YCB models the points span 0.99-1.0 of it;
#: a unit slip is a factor of 10 (cm) or 1000 (mm), a truncated or foreign points file usually more than 1.5.
DIAMETER_TOLERANCE = 1.5
#: Thresholds of the plotted accuracy curves, metres (the toolbox's 0..0.1 m range).
CURVE_THRESHOLDS = np.linspace(0.0, 0.1, 401)
COLOR_EST = (255, 140, 0)  # RGB orange
COLOR_GT = (40, 200, 60)  # RGB green


# ------------------------------------------------------------------------------------------ run loading


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
    objects: dict[str, dict[str, Any]] = {}
    objects_path = run_dir / "objects.json"
    if objects_path.is_file():
        try:
            objects = json.loads(objects_path.read_text())
        except json.JSONDecodeError as e:
            raise DataError(f"{objects_path}: invalid JSON ({e})") from None
        if not isinstance(objects, dict) or not all(isinstance(v, dict) for v in objects.values()):
            raise DataError(f"{objects_path}: expected {{obj_name: {{obj_id, mesh, points, diameter_m}}}}")
    run = RunData(run_dir=run_dir, poses=poses, gt=gt, frames=frames, objects=objects)
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
        return pts * unit_scale(label, np.stack([pts.min(axis=0), pts.max(axis=0)]), mesh_conf)
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
            try:
                pts = np.loadtxt(path, dtype=np.float64, ndmin=2)
            except (OSError, ValueError) as e:
                raise DataError(f"{where}: {name}.points: cannot read {path} ({e})") from None
            if pts.ndim != 2 or pts.shape[1] < 3 or len(pts) == 0:
                raise DataError(f"{where}: {name}.points: {path} must hold x y z per line, got {pts.shape}")
            if not np.all(np.isfinite(pts[:, :3])):
                raise DataError(f"{where}: {name}.points: {path} has NaN or infinite coordinates")
            pts = _points_to_metres(pts[:, :3], diam, mesh_conf, f"{where}: {name}.points: {path}")
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


# ---------------------------------------------------------------------------------------------- tables


def _paper_columns(summary: pd.DataFrame) -> pd.DataFrame:
    """Add the paper's per-object numbers; its mean only when some of our objects are the paper's."""
    known = set(PAPER_GNC_POSE) - {"mean"}
    overlap = bool(known & set(summary["obj_name"]))
    paper = [
        PAPER_GNC_POSE.get(n, (np.nan, np.nan)) if (n != "mean" or overlap) else (np.nan, np.nan)
        for n in summary["obj_name"]
    ]
    return summary.assign(paper_adds_auc=[p[0] for p in paper], paper_add_auc=[p[1] for p in paper])


def _instance_table(run: RunData, per_instance: pd.DataFrame) -> pd.DataFrame:
    """frames.csv with ground truth: per-instance errors plus frame ids and estimate diagnostics."""
    table = per_instance.copy()
    if run.frames is not None and {"scene_id", "im_id"} <= set(run.frames.columns):
        ids = run.frames.drop_duplicates("frame_id").set_index("frame_id")
        for c in ("scene_id", "im_id", "stamp_ns"):
            if c in ids.columns and c not in table.columns:
                table[c] = table["frame_id"].map(ids[c])
    diag = [
        c for c in ("reason", "n_matches", "n_inliers", "median_residual_px", "time_total_s") if c in run.poses.columns
    ]
    if diag:
        est = run.poses.assign(_ok=(run.poses["status"] == "ok").astype(int))
        est = est.sort_values(["_ok", "confidence"], ascending=False, kind="stable")
        est = est.drop_duplicates(["frame_id", "obj_name"])[["frame_id", "obj_name", *diag]]
        table = table.merge(est, on=["frame_id", "obj_name"], how="left")
    first = [
        c
        for c in ("frame_id", "scene_id", "im_id", "stamp_ns", "obj_name", "obj_id", "status", "reason")
        if c in table.columns
    ]
    return table[first + [c for c in table.columns if c not in first]]


def _detection_summary(poses: pd.DataFrame) -> pd.DataFrame:
    """summary.csv without ground truth: per object and ``all``, detection rate and confidence."""
    rows = []
    groups = [(n, poses[poses["obj_name"] == n]) for n in sorted(set(poses["obj_name"]))]
    for name, g in [*groups, ("all", poses)]:
        ok = g["status"] == "ok"
        row = {
            "obj_name": name,
            "n": len(g),
            "n_ok": int(ok.sum()),
            "detection_rate_pct": float(ok.mean() * 100.0) if len(g) else np.nan,
            "median_confidence": float(g.loc[ok, "confidence"].median()) if ok.any() else np.nan,
            "mean_confidence": float(g.loc[ok, "confidence"].mean()) if ok.any() else np.nan,
        }
        for s in STATUSES[1:]:
            row[f"n_{s}"] = int((g["status"] == s).sum())
        rows.append(row)
    return pd.DataFrame(rows)


def _timing_table(poses: pd.DataFrame) -> pd.DataFrame:
    rows = []
    total = float(poses["time_total_s"].sum()) if "time_total_s" in poses.columns else np.nan
    for stage in (*STAGES, "total"):
        col = f"time_{stage}_s"
        if col not in poses.columns or len(poses) == 0:
            continue
        v = poses[col].astype(float)
        rows.append(
            {
                "stage": stage,
                "total_s": float(v.sum()),
                "mean_ms": float(v.mean() * 1e3),
                "median_ms": float(v.median() * 1e3),
                "p95_ms": float(v.quantile(0.95) * 1e3),
                "share_pct": float(v.sum() / total * 100.0) if total > 0 else np.nan,
            }
        )
    return pd.DataFrame(rows, columns=["stage", "total_s", "mean_ms", "median_ms", "p95_ms", "share_pct"])


# ---------------------------------------------------------------------------------------------- figures


def _new_figure(w: float, h: float):
    # The object-oriented API with an Agg canvas: no pyplot global state, no display needed.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _fig_png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _colors(n: int) -> list:
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def _curve_figure(curves: list[tuple[str, np.ndarray, dict]], title: str) -> str:
    """Accuracy vs threshold; ``curves`` = (label, (n,) distances, line style kwargs)."""
    ncol = 1 if len(curves) <= 4 else 2
    legend_rows = -(-len(curves) // ncol)
    fig = _new_figure(5.8, 3.6 + 0.2 * legend_rows)
    ax = fig.add_subplot(1, 1, 1)
    x_cm = CURVE_THRESHOLDS * 100.0
    for label, d, style in curves:
        ax.step(x_cm, metrics.accuracy_curve(d, CURVE_THRESHOLDS), where="post", label=label, **style)
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 101)
    ax.set_xlabel("distance threshold (cm)")
    ax.set_ylabel("accuracy (%)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    # Below the axes: with a dozen objects a legend inside would hide the curves.
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=ncol, fontsize=7.5, frameon=False)
    fig.tight_layout()
    return _fig_png(fig)


def _object_curves(per_instance: pd.DataFrame, column: str) -> list[tuple[str, np.ndarray, dict]]:
    objects = sorted(set(per_instance["obj_name"]))
    curves = []
    for name, color in zip(objects, _colors(len(objects)), strict=True):
        d = per_instance.loc[per_instance["obj_name"] == name, column].to_numpy(float)
        curves.append((f"{name} (AUC {metrics.vocap_auc(d):.1f}, n={len(d)})", d, {"color": color, "lw": 1.4}))
    d = per_instance[column].to_numpy(float)
    curves.append(
        (f"pooled (AUC {metrics.vocap_auc(d):.1f}, n={len(d)})", d, {"color": "black", "lw": 2.2, "ls": "--"})
    )
    return curves


def _error_figure(per_instance: pd.DataFrame) -> str:
    ok = per_instance[per_instance["status"] == "ok"]
    fig = _new_figure(11.0, 3.4)
    panels = [
        ("adds_m", 1000.0, "ADD-S (mm)"),
        ("add_m", 1000.0, "ADD (mm)"),
        ("rot_err_deg", 1.0, "rotation error (deg)"),
        ("trans_err_mm", 1.0, "translation error (mm)"),
    ]
    for i, (col, scale, label) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        v = ok[col].to_numpy(float) * scale
        v = v[np.isfinite(v)]
        if v.size:
            ax.hist(v, bins=min(30, max(5, v.size)), color="#4c72b0", edgecolor="white")
            ax.axvline(float(np.median(v)), color="black", ls="--", lw=1, label=f"median {np.median(v):.1f}")
            ax.legend(fontsize=8, frameon=False)
        else:
            ax.text(0.5, 0.5, "no ok estimates", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel(label)
        ax.set_ylabel("instances" if i == 0 else "")
    fig.suptitle(
        f"Error distributions over {len(ok)} ok estimates ({len(per_instance) - len(ok)} failures not shown)",
        fontsize=10,
    )
    fig.tight_layout()
    return _fig_png(fig)


def _confidence_figure(per_instance: pd.DataFrame) -> str:
    from scipy.stats import spearmanr

    ok = per_instance[(per_instance["status"] == "ok") & np.isfinite(per_instance["adds_m"])]
    fig = _new_figure(7.6, 4.2)
    ax = fig.add_subplot(1, 1, 1)
    objects = sorted(set(per_instance["obj_name"]))
    for name, color in zip(objects, _colors(len(objects)), strict=True):
        g = ok[ok["obj_name"] == name]
        ax.scatter(
            g["confidence"],
            np.maximum(g["adds_m"] * 1000.0, 1e-2),
            s=18,
            color=color,
            label=name,
            alpha=0.8,
            edgecolors="none",
        )
    title = "Confidence vs ADD-S error (ok estimates)"
    if len(ok) >= 3 and ok["confidence"].nunique() > 1:
        rho = spearmanr(ok["confidence"], ok["adds_m"]).statistic
        title += f", Spearman rho = {rho:.2f}"
    ax.set_yscale("log")
    ax.set_xlim(-0.02, 1.02)
    ax.set_xlabel("confidence")
    ax.set_ylabel("ADD-S (mm, log)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    if objects:
        ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False)
    fig.tight_layout()
    return _fig_png(fig)


def _confidence_hist_figure(poses: pd.DataFrame) -> str:
    fig = _new_figure(7.6, 3.6)
    ax = fig.add_subplot(1, 1, 1)
    bins = np.linspace(0, 1, 21)
    ok = poses["status"] == "ok"
    ax.hist(
        [poses.loc[ok, "confidence"].astype(float), poses.loc[~ok, "confidence"].astype(float)],
        bins=bins,
        stacked=True,
        color=["#4c72b0", "#c44e52"],
        label=[f"ok ({int(ok.sum())})", f"failed ({int((~ok).sum())})"],
        edgecolor="white",
    )
    ax.set_xlabel("confidence")
    ax.set_ylabel("(frame, object) pairs")
    ax.set_title(
        f"Confidence distribution, detection rate {ok.mean() * 100:.1f} % ({int(ok.sum())} / {len(ok)})"
        if len(ok)
        else "Confidence distribution (no estimates)",
        fontsize=10,
    )
    ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    return _fig_png(fig)


#: What the timeline shows for a (frame, object) pair, most severe first, with its colour; a column that
#: holds several frames shows the most severe of them.
TIMELINE_KINDS: tuple[tuple[str, str], ...] = (
    ("ok but wrong (ADD-S > 0.1 d)", "#7b2d8e"),
    ("failed", "#c44e52"),
    ("low confidence", "#dd8452"),
    ("hidden", "#b0b0b0"),
    ("ok, full estimate", "#2f7d32"),
    ("ok, tracked", "#95d195"),
)
#: Most columns a timeline row has: a longer run puts several frames in a column.
TIMELINE_COLUMNS = 1200


def timeline_kinds(rows: pd.DataFrame, wrong: np.ndarray | None = None) -> np.ndarray:
    """Index into :data:`TIMELINE_KINDS` of each (frame, object) row (``status``, optional ``tracked``);
    ``wrong``: per row, True for an ok pose the ground truth rejects (ADD-S > 0.1 d)."""
    status = rows["status"].astype(str).to_numpy()
    tracked = rows["tracked"].eq(True).to_numpy() if "tracked" in rows.columns else np.zeros(len(rows), bool)
    ok = status == "ok"
    kind = np.full(len(rows), 1)  # failed: every status not named below
    kind[status == "low_confidence"] = 2
    kind[status == "hidden"] = 3
    kind[ok & ~tracked] = 4
    kind[ok & tracked] = 5
    if wrong is not None:
        kind[ok & wrong] = 0
    return kind


def timeline_grid(t_s: np.ndarray, obj: np.ndarray, kind: np.ndarray, objects: list[str], columns: int) -> np.ndarray:
    """(len(objects), columns) kind index of each column (-1: no row there): the time span cut into
    ``columns`` equal parts, each showing its most severe kind."""
    grid = np.full((len(objects), columns), len(TIMELINE_KINDS))
    span = float(t_s.max() - t_s.min()) if len(t_s) else 0.0
    col = np.zeros(len(t_s), int)
    if span > 0:
        col = np.minimum(((t_s - t_s.min()) / span * columns).astype(int), columns - 1)
    row = np.array([objects.index(o) for o in obj], int)
    np.minimum.at(grid, (row, col), kind)
    grid[grid == len(TIMELINE_KINDS)] = -1
    return grid


def _timeline_figure(poses: pd.DataFrame, per_instance: pd.DataFrame | None) -> str | None:
    """Status of each object over the run's time (and ADD-S, or confidence without ground truth); None for
    a run of one frame time."""
    if "stamp_ns" not in poses.columns or poses["stamp_ns"].isna().any():
        return None
    stamps = poses["stamp_ns"].astype("int64")
    if stamps.nunique() < 2:
        return None
    objects = sorted(set(poses["obj_name"]))
    t_s = ((stamps - stamps.min()) * 1e-9).to_numpy()
    wrong = None
    if per_instance is not None:
        key = per_instance.set_index(["frame_id", "obj_name"])
        idx = pd.MultiIndex.from_frame(poses[["frame_id", "obj_name"]])
        adds = key["adds_m"].reindex(idx).to_numpy(float)
        diam = key["diameter_m"].reindex(idx).to_numpy(float)
        wrong = adds > 0.1 * diam
    kind = timeline_kinds(poses, wrong)
    columns = min(TIMELINE_COLUMNS, int(stamps.nunique()))
    grid = timeline_grid(t_s, poses["obj_name"].to_numpy(), kind, objects, columns)
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    rgb = np.ones((*grid.shape, 3))  # white: no row there
    for k, (_, c) in enumerate(TIMELINE_KINDS):
        rgb[grid == k] = to_rgb(c)
    fig = _new_figure(10.0, 1.6 + 0.32 * len(objects) + 2.6)
    ax, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [0.5 + 0.32 * len(objects), 2.6]})
    ax.imshow(rgb, aspect="auto", interpolation="nearest", extent=(0, t_s.max(), len(objects) - 0.5, -0.5))
    ax.set_yticks(range(len(objects)), objects, fontsize=8)
    title = "Status over time"
    if columns < stamps.nunique():
        title += f" (about {stamps.nunique() / columns:.0f} frames a column: the most severe shown)"
    ax.set_title(title, fontsize=10)
    shown = sorted(set(kind.tolist()))
    ax.legend(
        handles=[Patch(color=TIMELINE_KINDS[k][1], label=TIMELINE_KINDS[k][0]) for k in shown],
        loc="upper left",
        bbox_to_anchor=(1.0, 1.0),
        frameon=False,
        fontsize=8,
    )
    colors = _colors(len(objects))
    ok = (poses["status"] == "ok").to_numpy()
    for name, c in zip(objects, colors, strict=True):
        sel = ok & (poses["obj_name"] == name).to_numpy()
        if per_instance is not None:
            ax2.scatter(t_s[sel], np.maximum(adds[sel] * 1000.0, 1e-2), s=6, color=c, label=name)
            d = diam[(poses["obj_name"] == name).to_numpy()]
            if np.isfinite(d).any():  # the 0.1 d line above which an ok pose counts as wrong
                ax2.axhline(100.0 * np.nanmax(d), color=c, ls="--", lw=0.8)
        else:
            ax2.scatter(t_s[sel], poses["confidence"].to_numpy(float)[sel], s=6, color=c, label=name)
    if per_instance is not None:
        ax2.set_yscale("log")
        ax2.set_ylabel("ADD-S of ok poses (mm; dashed: 0.1 d)")
    else:
        ax2.set_ylim(0, 1.02)
        ax2.set_ylabel("confidence of ok poses")
    ax2.set_xlabel("seconds since the run's first frame")
    ax2.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False, fontsize=8, markerscale=2)
    fig.tight_layout()
    return _fig_png(fig)


def _timeline_section(poses: pd.DataFrame, per_instance: pd.DataFrame | None) -> list[str]:
    png = _timeline_figure(poses, per_instance)
    if png is None:
        return []
    what = "ADD-S of the ok poses" if per_instance is not None else "confidence of the ok poses"
    return [
        '<section id="timeline"><h2>Over time</h2>',
        (
            '<p class="note">Each object\'s status frame by frame (white: not estimated there), and the '
            f"{what}: where in the log an object was lost, tracked or wrong.</p>"
        ),
        _img("plot-timeline", f"Status of each object over time, and the {what}", png),
        "</section>",
    ]


# ---------------------------------------------------------------------------------------------- gallery

_BOX_EDGES = ((0, 1), (1, 3), (3, 2), (2, 0), (4, 5), (5, 7), (7, 6), (6, 4), (0, 4), (1, 5), (2, 6), (3, 7))


def _project(cam_from_model: np.ndarray, pts: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N, 2) pixel coordinates of model points; NaN rows for points at or behind the camera."""
    cam = pts @ cam_from_model[:3, :3].T + cam_from_model[:3, 3]
    uv = np.full((len(pts), 2), np.nan)
    front = cam[:, 2] > 1e-6
    if front.any():
        proj, _ = cv2.projectPoints(
            cam[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist if dist.size else None
        )
        uv[front] = proj.reshape(-1, 2)
    return uv


def draw_overlay(
    rgb: np.ndarray,
    K: np.ndarray,
    pts: np.ndarray,
    poses: list[tuple[np.ndarray, tuple[int, int, int]]],
    dist: np.ndarray | None = None,
    out_height: int = 200,
) -> np.ndarray:
    """Draw model points and their 3D bounding box at each pose, cropped around the object.

    Args:
        rgb: (H, W, 3) uint8 RGB frame.
        K: (3, 3) intrinsics.
        pts: (N, 3) model points, metres.
        poses: (4x4 cam_from_model, RGB colour) pairs, drawn in order (last on top).
        dist: OpenCV distortion coefficients (empty or None: none).
        out_height: height of the returned image in pixels.

    Returns:
        (out_height, W', 3) uint8 RGB image.
    """
    dist = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    sub = pts[:: max(1, len(pts) // 400)]
    projected = [(_project(T, sub, K, dist), _project(T, corners, K, dist), c) for T, c in poses]
    h, w = rgb.shape[:2]
    # Crop around what was drawn (with context), so a small object is visible in a thumbnail.
    all_uv = np.concatenate([np.concatenate([a, b]) for a, b, _ in projected]) if projected else np.zeros((0, 2))
    all_uv = all_uv[np.all(np.isfinite(all_uv), axis=1)]
    all_uv = all_uv[(all_uv[:, 0] > -w) & (all_uv[:, 0] < 2 * w) & (all_uv[:, 1] > -h) & (all_uv[:, 1] < 2 * h)]
    x0, y0, x1, y1 = 0, 0, w, h
    if len(all_uv):
        (ux0, uy0), (ux1, uy1) = all_uv.min(axis=0), all_uv.max(axis=0)
        # A 4:3 window around the drawing, shifted (not clipped) to stay inside the frame, so every
        # thumbnail has the same shape.
        ch = min(float(h), max(ux1 - ux0, uy1 - uy0, 40.0) * 1.6)
        cw = min(float(w), ch * 4 / 3)
        cx = min(max((ux0 + ux1) / 2, cw / 2), w - cw / 2)
        cy = min(max((uy0 + uy1) / 2, ch / 2), h - ch / 2)
        x0, x1 = round(cx - cw / 2), round(cx + cw / 2)
        y0, y1 = round(cy - ch / 2), round(cy + ch / 2)
    scale = out_height / (y1 - y0)
    out_w = max(1, round((x1 - x0) * scale))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    img = np.ascontiguousarray(cv2.resize(rgb[y0:y1, x0:x1], (out_w, out_height), interpolation=interp))
    shift = 8  # fixed-point sub-pixel drawing
    for k, (uv_pts, uv_box, color) in enumerate(projected):
        # Earlier poses (ground truth) are drawn thicker, so an exact estimate on top leaves them visible.
        thickness = 2 if k == len(projected) - 1 else 4
        for u, v in (uv_pts - (x0, y0)) * scale:
            if np.isfinite(u) and np.isfinite(v):
                cv2.circle(
                    img,
                    (int(u * (1 << shift)), int(v * (1 << shift))),
                    1 << shift,
                    color,
                    -1,
                    cv2.LINE_AA,
                    shift,
                )
        box = (uv_box - (x0, y0)) * scale
        if np.all(np.isfinite(box)) and np.all(np.abs(box) < 1e5):
            for a, b in _BOX_EDGES:
                pa = tuple(int(c * (1 << shift)) for c in box[a])
                pb = tuple(int(c * (1 << shift)) for c in box[b])
                cv2.line(img, pa, pb, color, thickness, cv2.LINE_AA, shift)
    return img


def _png_b64(rgb: np.ndarray) -> str:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise DataError("cannot encode overlay PNG")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def _fetch_frames(run: RunData, frame_ids: set[str]) -> tuple[dict[str, Any], str]:
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


@dataclass
class _Case:
    group: str
    frame_id: str
    obj_name: str
    caption: str
    est: np.ndarray | None
    gt: np.ndarray | None


def _select_cases(run: RunData, per_instance: pd.DataFrame | None) -> list[_Case]:
    cases: list[_Case] = []
    est_by_key = {}
    for r in run.poses.to_dict("records"):
        T = row_cam_from_model(r) if r["status"] == "ok" else None
        key = (r["frame_id"], r["obj_name"])
        if key not in est_by_key or (T is not None and est_by_key[key][0] is None):
            est_by_key[key] = (T, r)
    if per_instance is not None:
        gt_by_key = {(r["frame_id"], r["obj_name"]): r for r in run.gt.to_dict("records")}
        ok = per_instance[(per_instance["status"] == "ok") & np.isfinite(per_instance["adds_m"])]
        ok = ok.sort_values("adds_m", kind="stable")
        best = ok.head(GALLERY_K)
        worst = ok.drop(best.index).tail(GALLERY_K).iloc[::-1]
        failed = per_instance[per_instance["status"] != "ok"].head(GALLERY_K)
        for group, rows in (("best", best), ("worst", worst), ("failed", failed)):
            for r in rows.to_dict("records"):
                key = (r["frame_id"], r["obj_name"])
                g = gt_by_key[key]
                T_gt = np.eye(4)
                T_gt[:3, :3] = np.asarray(g["R"], dtype=float).reshape(3, 3)
                T_gt[:3, 3] = np.asarray(g["t_m"], dtype=float).reshape(3)
                est = est_by_key.get(key, (None, {}))
                if group == "failed":
                    reason = est[1].get("reason", "") if est[1] else ""
                    caption = f"{r['status']}" + (f": {reason}" if reason else "") + " (ground truth only)"
                else:
                    caption = (
                        f"ADD-S {r['adds_m'] * 1000:.1f} mm, ADD {r['add_m'] * 1000:.1f} mm, "
                        f"rot {r['rot_err_deg']:.1f}°, conf {r['confidence']:.2f}"
                    )
                cases.append(_Case(group, key[0], key[1], caption, est[0], T_gt))
    else:
        ok = run.poses[run.poses["status"] == "ok"].sort_values("confidence", ascending=False, kind="stable")
        top = ok.head(GALLERY_K)
        low = ok.drop(top.index).tail(GALLERY_K).iloc[::-1]
        for group, rows in (("most confident", top), ("least confident", low)):
            for r in rows.to_dict("records"):
                caption = f"conf {r['confidence']:.2f}, {int(r.get('n_inliers', 0))} inliers"
                cases.append(_Case(group, r["frame_id"], r["obj_name"], caption, row_cam_from_model(r), None))
    return cases


def _gallery(run: RunData, per_instance: pd.DataFrame | None) -> tuple[list[dict], str]:
    """Overlay images as dicts (id, group, title, caption, b64) and a note explaining any gap."""
    cases = _select_cases(run, per_instance)
    if not cases:
        return [], "no estimates to show"
    names = {c.obj_name for c in cases}
    try:
        points, _ = run.model_points(names)
    except BatchposeError as e:
        return [], f"no model points to draw ({e})"
    frames, note = _fetch_frames(run, {c.frame_id for c in cases})
    if not frames:
        return [], note
    from batchpose.core.frames import decode_image

    items = []
    counters: dict[str, int] = {}
    problems = []
    for case in cases:
        frame = frames.get(case.frame_id)
        if frame is None:
            continue
        try:
            rgb = decode_image(frame)
        except BatchposeError as e:
            problems.append(str(e))
            continue
        draw = [(T, c) for T, c in ((case.gt, COLOR_GT), (case.est, COLOR_EST)) if T is not None]
        img = draw_overlay(
            rgb,
            np.asarray(frame.camera.K, float),
            points[case.obj_name],
            draw,
            dist=np.asarray(frame.camera.dist, float),
        )
        counters[case.group] = counters.get(case.group, 0) + 1
        slug = case.group.replace(" ", "-")
        items.append(
            {
                "id": f"overlay-{slug}-{counters[case.group]}",
                "group": case.group,
                "title": f"{case.frame_id} · {case.obj_name}",
                "caption": case.caption,
                "b64": _png_b64(img),
            }
        )
    if problems:
        note = "; ".join(filter(None, [note, f"{len(problems)} frames could not be decoded ({problems[0]})"]))
    return items, note


# ------------------------------------------------------------------------------------------------ HTML

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 24px auto;
       max-width: 1180px; padding: 0 16px; color: #1d1d1f; background: #fff; line-height: 1.4; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ddd; padding-bottom: 4px;
     margin-top: 1.8em; } h3 { margin-bottom: 0.3em; }
.meta, .note { color: #555; font-size: 0.9em; }
table { border-collapse: collapse; font-size: 0.88em; margin: 8px 0; }
th, td { border: 1px solid #d0d0d0; padding: 4px 8px; text-align: right; }
th { background: #f3f4f6; } td:first-child, th:first-child { text-align: left; }
tr.agg td { font-weight: 600; background: #fafafa; }
td.paper, th.paper { background: #f4f0fa; color: #4b3b6b; }
img.plot { max-width: 100%; display: block; margin: 8px 0; }
.plots { display: flex; flex-wrap: wrap; gap: 8px; align-items: flex-start; }
.plots img.plot { max-width: calc(50% - 4px); }
.gallery { display: flex; flex-wrap: wrap; gap: 12px; }
figure { margin: 0; border: 1px solid #ddd; padding: 6px; background: #fafafa; width: min-content; }
figure img { display: block; height: 200px; }
figcaption { font-size: 0.78em; overflow-wrap: anywhere; }
.swatch { display: inline-block; width: 12px; height: 12px; vertical-align: middle; margin: 0 3px 0 10px; }
pre { background: #f6f8fa; padding: 10px; overflow-x: auto; font-size: 0.82em; }
.warn { color: #8a4b00; background: #fff6e5; padding: 6px 10px; border-left: 3px solid #e0a030; }
"""


def _esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _fmt(x: Any, digits: int = 1) -> str:
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)):
        return _esc(x)
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    v = float(x)
    if np.isnan(v):
        return "–"
    if np.isinf(v):
        return "∞"
    return f"{v:.{digits}f}"


def _img(id_: str, alt: str, b64: str, cls: str = "plot") -> str:
    return f'<img class="{cls}" id="{_esc(id_)}" alt="{_esc(alt)}" src="data:image/png;base64,{b64}">'


def _table(df: pd.DataFrame, id_: str, headers: Mapping[str, str] | None = None, digits: int = 1) -> str:
    headers = headers or {}
    head = "".join(f"<th>{_esc(headers.get(c, c))}</th>" for c in df.columns)
    body = "".join(
        "<tr>" + "".join(f"<td>{_fmt(v, digits)}</td>" for v in row) + "</tr>" for row in df.itertuples(index=False)
    )
    return f'<table id="{_esc(id_)}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _failures_text(row: Mapping[str, Any]) -> str:
    parts = [f"{s} {int(row[f'n_{s}'])}" for s in metrics.FAILURE_STATUSES if row.get(f"n_{s}", 0)]
    return ", ".join(parts) or "–"


def _results_table(summary: pd.DataFrame) -> str:
    head = (
        "<tr><th>Object</th><th>n</th><th>ADD-S AUC</th><th>ADD AUC</th>"
        '<th class="paper">paper ADD-S AUC†</th><th class="paper">paper ADD AUC†</th>'
        "<th>ADD-S &lt; 0.1d (%)</th><th>ADD &lt; 0.1d (%)</th><th>median rot err (°)</th>"
        "<th>median trans err (mm)</th><th>ok</th><th>failures</th></tr>"
    )
    rows = []
    for r in summary.to_dict("records"):
        cls = ' class="agg"' if r["obj_name"] in ("mean", "pooled") else ""
        label = {"mean": "mean of objects", "pooled": "pooled (all instances)"}.get(r["obj_name"], r["obj_name"])
        rows.append(
            f"<tr{cls}><td>{_esc(label)}</td><td>{int(r['n'])}</td><td>{_fmt(r['adds_auc'])}</td>"
            f'<td>{_fmt(r["add_auc"])}</td><td class="paper">{_fmt(r["paper_adds_auc"])}</td>'
            f'<td class="paper">{_fmt(r["paper_add_auc"])}</td><td>{_fmt(r["adds_recall_01d"])}</td>'
            f"<td>{_fmt(r['add_recall_01d'])}</td><td>{_fmt(r['median_rot_err_deg'])}</td>"
            f"<td>{_fmt(r['median_trans_err_mm'])}</td><td>{int(r['n_ok'])}</td>"
            f"<td>{_esc(_failures_text(r))}</td></tr>"
        )
    return f'<table id="results-table"><thead>{head}</thead><tbody>{"".join(rows)}</tbody></table>'


def _page(title: str, body: list[str]) -> str:
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{_esc(title)}</title><style>{_CSS}</style></head>\n<body>\n" + "\n".join(body) + "\n</body></html>\n"
    )


def _metadata_sections(run: RunData) -> list[str]:
    out = ['<section id="run"><h2>Run</h2>']
    status = run.poses["status"].value_counts().rename_axis("status").reset_index(name="count")
    out.append("<h3>Status of (frame, object) pairs</h3>" + _table(status, "status-table"))
    if "reason" in run.poses.columns:
        reasons = run.poses.loc[run.poses["status"] != "ok", "reason"].value_counts().head(10)
        if len(reasons):
            out.append(
                "<h3>Most frequent failure reasons</h3>"
                + _table(reasons.rename_axis("reason").reset_index(name="count"), "reasons-table")
            )
    timing = _timing_table(run.poses)
    if len(timing):
        out.append(
            "<h3>Timings by stage (per frame and object)</h3>"
            + _table(
                timing,
                "timing-table",
                {
                    "total_s": "total (s)",
                    "mean_ms": "mean (ms)",
                    "median_ms": "median (ms)",
                    "p95_ms": "p95 (ms)",
                    "share_pct": "share (%)",
                },
                digits=2,
            )
        )
    if run.versions:
        vers = pd.DataFrame(
            [(k, v if isinstance(v, str) else json.dumps(v)) for k, v in run.versions.items()],
            columns=["package", "version"],
        )
        out.append("<h3>Versions</h3>" + _table(vers, "versions-table"))
    if run.manifest is not None:
        out.append("<h3>Data manifest</h3><pre>" + _esc(yaml.safe_dump(run.manifest, sort_keys=False)) + "</pre>")
    if run.config_text:
        out.append("<h3>Resolved config</h3><pre>" + _esc(run.config_text) + "</pre>")
    for note in run.notes:
        out.append(f'<p class="warn">{_esc(note)}</p>')
    out.append("</section>")
    return out


def _gallery_section(items: list[dict], note: str, with_gt: bool) -> list[str]:
    legend = f'<span class="swatch" style="background:rgb{COLOR_EST}"></span>estimate' + (
        f'<span class="swatch" style="background:rgb{COLOR_GT}"></span>ground truth' if with_gt else ""
    )
    out = [
        '<section id="gallery"><h2>Overlays</h2>',
        f'<p class="note">Model points and 3D bounding box drawn at the pose: {legend}.</p>',
    ]
    if note:
        out.append(f'<p class="warn" id="gallery-note">Gallery: {_esc(note)}</p>')
    groups: dict[str, list[dict]] = {}
    for it in items:
        groups.setdefault(it["group"], []).append(it)
    for group, its in groups.items():
        out.append(f'<h3>{_esc(group.capitalize())}</h3><div class="gallery">')
        for it in its:
            out.append(
                "<figure>"
                + _img(it["id"], f"{group} case: {it['title']}", it["b64"], cls="overlay")
                + f"<figcaption><b>{_esc(it['title'])}</b><br>{_esc(it['caption'])}</figcaption></figure>"
            )
        out.append("</div>")
    out.append("</section>")
    return out


# ------------------------------------------------------------------------------------------------ I/O


def _write_atomic(path: Path, data: str) -> None:
    write_text_atomic(path, data)


def _write_csv(df: pd.DataFrame, path: Path) -> None:
    _write_atomic(path, df.to_csv(index=False, lineterminator="\n"))


def _score(run: RunData) -> tuple[pd.DataFrame, pd.DataFrame]:
    points, diameters = run.model_points(run.gt["obj_name"])
    per_instance, summary = metrics.score(run.poses, run.gt, points, diameters)
    return per_instance, _paper_columns(summary)


def _is_up_to_date(index: Path, run_dir: Path) -> bool:
    if not index.is_file():
        return False
    inputs = [run_dir / n for n in ("poses.parquet", "gt.parquet", "objects.json", "frames.parquet")]
    newest = max((p.stat().st_mtime for p in inputs if p.exists()), default=0.0)
    return index.stat().st_mtime >= newest


def main(run_dir: Path, overwrite: bool = False) -> Path:
    """Score a run and write ``run_dir/report/{summary.csv, frames.csv, index.html}``.

    Args:
        run_dir: run directory (layout in the module docstring).
        overwrite: rebuild even when the report is newer than the run's tables.

    Returns:
        The report directory.

    Raises:
        DataError: ``poses.parquet`` missing or a table malformed; objects without model points.
    """
    run_dir = Path(run_dir)
    report_dir = run_dir / "report"
    index = report_dir / "index.html"
    if not overwrite and _is_up_to_date(index, run_dir):
        log.info("Skipping report: %s is up to date", index)
        return report_dir
    run = load_run(run_dir)
    report_dir.mkdir(parents=True, exist_ok=True)
    title = f"batchpose report: {run_dir.resolve().name}"
    n_frames = len(run.frames) if run.frames is not None else run.poses["frame_id"].nunique()
    n_ok = int((run.poses["status"] == "ok").sum())
    body = [
        f"<h1>{_esc(title)}</h1>",
        (
            f'<p class="meta">{_esc(run_dir.resolve())} · {n_frames} frames · {len(run.poses)} (frame, object) '
            f"pairs, {n_ok} ok · generated {_dt.datetime.now(_dt.UTC).strftime('%Y-%m-%d %H:%M UTC')}</p>"
        ),
    ]
    if run.has_gt:
        per_instance, summary = _score(run)
        _write_csv(summary, report_dir / "summary.csv")
        _write_csv(_instance_table(run, per_instance), report_dir / "frames.csv")
        means = " · ".join(f"{k} {a:.1f} / {b:.1f}" for k, (a, b) in PAPER_MEANS.items())
        body += [
            '<section id="results"><h2>Results</h2>',
            (
                '<p class="note">AUC: area under the accuracy–threshold curve up to 10 cm, YCB-Video toolbox '
                "definition (a missing or failed estimate counts as a failure; with few instances an object's "
                "AUC is biased up by about 100/n). 0.1d: 10 % of the object diameter.</p>"
            ),
            _results_table(summary),
            (
                f'<p class="note">† GNC-Pose\'s numbers {_esc(PAPER_NOTE)}. Paper means, ADD-S AUC / ADD AUC: '
                f"{_esc(means)}.</p></section>"
            ),
            *_timeline_section(run.poses, per_instance),
            '<section id="curves"><h2>Accuracy–threshold curves</h2><div class="plots">',
            _img(
                "plot-curve-adds",
                "ADD-S accuracy vs threshold, per object and pooled",
                _curve_figure(_object_curves(per_instance, "adds_m"), "ADD-S"),
            ),
            _img(
                "plot-curve-add",
                "ADD accuracy vs threshold, per object and pooled",
                _curve_figure(_object_curves(per_instance, "add_m"), "ADD"),
            ),
            "</div></section>",
            '<section id="errors"><h2>Error distributions</h2>',
            _img(
                "plot-errors",
                "Histograms of ADD-S, ADD, rotation and translation error",
                _error_figure(per_instance),
            ),
            "</section>",
            '<section id="confidence"><h2>Confidence vs error</h2>',
            _img(
                "plot-confidence",
                "Scatter of confidence against ADD-S error",
                _confidence_figure(per_instance),
            ),
            "</section>",
        ]
        items, note = _gallery(run, per_instance)
        pooled = summary.set_index("obj_name").loc["pooled"]
        headline = f"ADD-S AUC {pooled['adds_auc']:.1f}, ADD AUC {pooled['add_auc']:.1f} (pooled)"
    else:
        summary = _detection_summary(run.poses)
        _write_csv(summary, report_dir / "summary.csv")
        cols = [
            c
            for c in (
                "frame_id",
                "scene_id",
                "im_id",
                "stamp_ns",
                "obj_name",
                "obj_id",
                "status",
                "reason",
                "confidence",
                "n_matches",
                "n_inliers",
                "median_residual_px",
                "time_total_s",
            )
            if c in run.poses.columns
        ]
        _write_csv(run.poses[cols], report_dir / "frames.csv")
        body += [
            '<section id="results"><h2>Detections (no ground truth)</h2>',
            (
                '<p class="note">This run has no ground truth, so accuracy cannot be measured; the detection '
                "rate is ok / all (frame, object) pairs.</p>"
            ),
            _table(
                summary[
                    [
                        "obj_name",
                        "n",
                        "n_ok",
                        "detection_rate_pct",
                        "median_confidence",
                        *[f"n_{s}" for s in STATUSES[1:]],
                    ]
                ],
                "results-table",
                {
                    "obj_name": "Object",
                    "n_ok": "ok",
                    "detection_rate_pct": "detection rate (%)",
                    "median_confidence": "median confidence (ok)",
                },
                digits=2,
            ),
            "</section>",
            *_timeline_section(run.poses, None),
            '<section id="confidence"><h2>Confidence</h2>',
            _img(
                "plot-confidence",
                "Histogram of confidence, ok and failed",
                _confidence_hist_figure(run.poses),
            ),
            "</section>",
        ]
        items, note = _gallery(run, None)
        headline = f"detection rate {summary['detection_rate_pct'].iloc[-1]:.1f} %"
    body += _gallery_section(items, note, with_gt=run.has_gt)
    body += _metadata_sections(run)
    _write_atomic(index, _page(title, body))
    log.info("report: %s (%s; %d overlays%s)", index, headline, len(items), f"; {note}" if note else "")
    return report_dir


# --------------------------------------------------------------------------------------------- compare


def _run_labels(run_dirs: list[Path]) -> list[str]:
    """Folder names, or the last two path parts where names collide (``a/run``, ``b/run``)."""
    paths = [p.resolve() for p in run_dirs]
    names = [p.name for p in paths]
    labels = [f"{p.parent.name}/{p.name}" if names.count(p.name) > 1 else p.name for p in paths]
    for i, label in enumerate(labels):
        while label in labels[:i]:
            label += "'"
        labels[i] = label
    return labels


def compare(run_dirs: list[Path], out: Path) -> Path:
    """Compare runs side by side: ``out/compare.csv`` (one row per run) and ``out/index.html``.

    Args:
        run_dirs: run directories (labelled by folder name; duplicates get a suffix).
        out: output directory.

    Returns:
        The output directory.
    """
    if not run_dirs:
        raise DataError("compare: no run directories given")
    out = Path(out)
    rows, curves, notes = [], {"adds_m": [], "add_m": []}, []
    labels = _run_labels([Path(p) for p in run_dirs])
    colors = _colors(len(run_dirs))
    for run_dir, label, color in zip(run_dirs, labels, colors, strict=True):
        run = load_run(Path(run_dir))
        ok = run.poses["status"] == "ok"
        n_frames = len(run.frames) if run.frames is not None else run.poses["frame_id"].nunique()
        row: dict[str, Any] = {
            "run": label,
            "run_dir": str(Path(run_dir).resolve()),
            "n_frames": n_frames,
            "n_pairs": len(run.poses),
            "n_ok": int(ok.sum()),
            "detection_rate_pct": float(ok.mean() * 100.0) if len(ok) else np.nan,
            "time_per_pair_s": float(run.poses["time_total_s"].mean())
            if "time_total_s" in run.poses.columns and len(run.poses)
            else np.nan,
        }
        if run.has_gt:
            per_instance, summary = _score(run)
            s = summary.set_index("obj_name")
            row.update(
                {
                    "n_instances": int(s.loc["pooled", "n"]),
                    "adds_auc_mean": s.loc["mean", "adds_auc"],
                    "add_auc_mean": s.loc["mean", "add_auc"],
                    "adds_auc_pooled": s.loc["pooled", "adds_auc"],
                    "add_auc_pooled": s.loc["pooled", "add_auc"],
                    "adds_recall_01d": s.loc["pooled", "adds_recall_01d"],
                    "add_recall_01d": s.loc["pooled", "add_recall_01d"],
                    "median_rot_err_deg": s.loc["pooled", "median_rot_err_deg"],
                    "median_trans_err_mm": s.loc["pooled", "median_trans_err_mm"],
                }
            )
            for obj in s.index.drop(["mean", "pooled"]):
                row[f"adds_auc[{obj}]"] = s.loc[obj, "adds_auc"]
                row[f"add_auc[{obj}]"] = s.loc[obj, "add_auc"]
            for col, lines in curves.items():
                d = per_instance[col].to_numpy(float)
                lines.append((f"{label} (AUC {metrics.vocap_auc(d):.1f}, n={len(d)})", d, {"color": color, "lw": 1.8}))
        else:
            notes.append(f"{label}: no ground truth, so no accuracy and no curve")
        rows.append(row)
    table = pd.DataFrame(rows)
    out.mkdir(parents=True, exist_ok=True)
    _write_csv(table, out / "compare.csv")
    show = [
        c
        for c in (
            "run",
            "n_frames",
            "n_pairs",
            "n_ok",
            "detection_rate_pct",
            "adds_auc_mean",
            "add_auc_mean",
            "adds_auc_pooled",
            "add_auc_pooled",
            "adds_recall_01d",
            "add_recall_01d",
            "median_rot_err_deg",
            "median_trans_err_mm",
            "time_per_pair_s",
        )
        if c in table.columns
    ]
    heads = {
        "detection_rate_pct": "detection (%)",
        "adds_auc_mean": "ADD-S AUC (mean)",
        "add_auc_mean": "ADD AUC (mean)",
        "adds_auc_pooled": "ADD-S AUC (pooled)",
        "add_auc_pooled": "ADD AUC (pooled)",
        "adds_recall_01d": "ADD-S < 0.1d (%)",
        "add_recall_01d": "ADD < 0.1d (%)",
        "median_rot_err_deg": "median rot (°)",
        "median_trans_err_mm": "median trans (mm)",
        "time_per_pair_s": "s / (frame, object)",
    }
    body = [
        "<h1>batchpose: comparison of runs</h1>",
        (
            f'<p class="meta">{len(run_dirs)} runs · generated '
            f"{_dt.datetime.now(_dt.UTC).strftime('%Y-%m-%d %H:%M UTC')}</p>"
        ),
        '<section id="results"><h2>Runs</h2>',
        _table(table[show], "compare-table", heads, digits=2),
    ]
    body += [f'<p class="warn">{_esc(n)}</p>' for n in notes]
    body.append("</section>")
    if curves["adds_m"]:
        body += [
            '<section id="curves"><h2>Accuracy–threshold curves (pooled instances)</h2><div class="plots">',
            _img(
                "plot-compare-adds",
                "ADD-S accuracy vs threshold, one curve per run",
                _curve_figure(curves["adds_m"], "ADD-S"),
            ),
            _img(
                "plot-compare-add",
                "ADD accuracy vs threshold, one curve per run",
                _curve_figure(curves["add_m"], "ADD"),
            ),
            "</div></section>",
        ]
    _write_atomic(out / "index.html", _page("batchpose: comparison of runs", body))
    log.info("compare: %d runs -> %s", len(run_dirs), out / "index.html")
    return out

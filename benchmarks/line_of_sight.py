"""Line of sight: what limits a pose's translation along the viewing ray on real frames, and what would pin it.

For each finished run (poses.parquet, gt.parquet, objects.json, manifest.yaml), every ground-truth instance with
an ``ok`` estimate is split into its translation error along the ground truth's viewing ray (signed: + is
too far; mm and % of the distance) and across it (mm), its rotation error and the ratio |t_est| / |t_gt| (a
wrong focal length or mesh scale shows as one constant ratio). Printed per object and per video:

1. the error split, for "right" poses (rotation error under ``--max-rot-deg``);
2. the causes, on the frames' depth images (``batchpose.io.sources.open_frames``; skipped with ``--no-depth``):
   the mesh rendered at the ground-truth pose and at the estimate, each compared with the sensor's depth
   inside the ground truth's silhouette (median rendered minus measured, mm and %: the ground truth's, the
   depth's and the calibration's consistency; a constant % is a scale);
3. SIFT's localisation: the along-ray error its inliers predict (one sigma, % of the distance:
   ``sigma_px / sqrt(sum |x_i - mean|^2)`` with ``sigma_px = median_residual_px / 1.177``, the image-space
   least-squares scale of ``n_inliers`` points) against the measured scatter;
4. the sequence: per video and object, the mean and the scatter of the along-ray error over the frames, and
   ADD < 0.1 d as it is, with the along-ray error removed, with only its per-sequence mean removed (what one
   external reference a sequence would pin: a depth frame, a known size) and with only its scatter removed
   (what averaging the frames of a static object could give);
5. the camera's travel over each video (the parallax a static scene's frames hold) and its elevation above
   the table (the plane the ground-truth poses rest on, :func:`batchpose.method.support.support_plane`, or
   one object's, ``one_object_plane``; the angle between it and the ray to each object's centre);
6. with two or more runs (e.g. the default and ``rgbd``): the along-ray error side by side on the pairs
   every run got right.

Usage:
    python benchmarks/line_of_sight.py RUN_DIR [RUN_DIR...] [--max-rot-deg 10] [--no-depth]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import code_version, machine, table  # noqa: E402

from batchpose.core.frames import decode_depth, decode_image  # noqa: E402
from batchpose.core.geometry import rotation_error_deg  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.io.sources import open_frames  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402
from batchpose.report.metrics import add, pick_estimates  # noqa: E402
from batchpose.report.runs import RunData, load_run  # noqa: E402

#: Median of the norm of a 2D residual with an isotropic Gaussian of sigma 1 per axis: sqrt(2 ln 2).
MEDIAN_NORM_PER_SIGMA = float(np.sqrt(2 * np.log(2)))
#: Sensor pixels farther than this from the rendered surface are another object or the background.
DEPTH_GATE_M = 0.03
#: Pixels of the rendered silhouette's rim left out (the sensor's depth edges are a pixel or two off).
RIM_PX = 3


def decompose(t_est: np.ndarray, t_gt: np.ndarray) -> dict[str, np.ndarray]:
    """Split translation errors into the part along the ground truth's viewing ray and the part across it.

    Args:
        t_est: (N, 3) or (3,) estimated translations, metres (camera frame).
        t_gt: the same shape, ground-truth translations, metres.

    Returns:
        ``along_m`` (N,) signed error along the unit ray ``t_gt / |t_gt|`` (+: the estimate is too far),
        ``along_pct`` (N,) the same in % of ``|t_gt|``, ``across_m`` (N,) the norm of the rest,
        ``ratio`` (N,) ``|t_est| / |t_gt|`` (a scale error of focal length or mesh: one constant ratio).

    Raises:
        ValueError: shapes differ or are not (N, 3), or a ground-truth translation is zero.
    """
    e = np.atleast_2d(np.asarray(t_est, dtype=np.float64))
    g = np.atleast_2d(np.asarray(t_gt, dtype=np.float64))
    if e.shape != g.shape or e.shape[1] != 3:
        raise ValueError(f"t_est and t_gt must both be (N, 3), got {e.shape} and {g.shape}")
    dist = np.linalg.norm(g, axis=1)
    if np.any(dist <= 0):
        raise ValueError("a ground-truth translation is zero: no viewing ray")
    ray = g / dist[:, None]
    d = e - g
    along = np.einsum("ij,ij->i", d, ray)
    across = np.linalg.norm(d - along[:, None] * ray, axis=1)
    return {
        "along_m": along,
        "along_pct": 100.0 * along / dist,
        "across_m": across,
        "ratio": np.linalg.norm(e, axis=1) / dist,
    }


def predicted_along_pct(inliers_px: np.ndarray, median_residual_px: float) -> float:
    """One-sigma along-ray error, % of the distance, that the inliers' image noise alone would give.

    The distance of an object of known size is its image scale; the least-squares scale of points ``x_i``
    with isotropic noise ``sigma`` per axis has a relative sigma of ``sigma / sqrt(sum |x_i - mean|^2)``.

    Args:
        inliers_px: (N, 2) inlier image positions, pixels.
        median_residual_px: the pose's median reprojection residual norm over the inliers, pixels.

    Returns:
        The predicted sigma in %, NaN with fewer than 3 inliers or no residual.
    """
    x = np.asarray(inliers_px, dtype=np.float64).reshape(-1, 2)
    if len(x) < 3 or not np.isfinite(median_residual_px):
        return float("nan")
    spread = float(np.sqrt(((x - x.mean(axis=0)) ** 2).sum()))
    return 100.0 * median_residual_px / MEDIAN_NORM_PER_SIGMA / spread


def video_of(frame_id: str) -> str:
    """``0000/000001`` -> ``0000``; ``data_syn/000003`` -> ``data_syn``; a frame id without a folder: ``-``."""
    return frame_id.split("/")[0] if "/" in frame_id else "-"


def _rt(row) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(row["R"], float).reshape(3, 3), np.asarray(row["t_m"], float)


def pair_table(run: RunData) -> pd.DataFrame:
    """One row per ground-truth instance with an ok estimate: the error split, ADD and SIFT's figures."""
    est = pick_estimates(run.poses)
    by_key = {(r["frame_id"], r["obj_name"]): r for r in est.to_dict("records")}
    points, diameters = run.model_points(run.gt["obj_name"].unique())
    rows = []
    for g in run.gt.to_dict("records"):
        e = by_key.get((g["frame_id"], g["obj_name"]))
        if e is None or e["status"] != "ok":
            continue
        (R_e, t_e), (R_g, t_g) = _rt(e), _rt(g)
        split = {k: float(v[0]) for k, v in decompose(t_e, t_g).items()}
        ray = t_g / np.linalg.norm(t_g)
        pts, d = points[g["obj_name"]], diameters[g["obj_name"]]
        rows.append(
            {
                "frame_id": g["frame_id"],
                "video": video_of(g["frame_id"]),
                "obj_name": g["obj_name"],
                "z_m": float(np.linalg.norm(t_g)),
                "rot_deg": rotation_error_deg(R_e, R_g),
                **split,
                "diameter_m": d,
                "add_m": add(R_e, t_e, R_g, t_g, pts),
                "add_no_along_m": add(R_e, t_e - split["along_m"] * ray, R_g, t_g, pts),
                "n_inliers": int(e.get("n_inliers", 0)),
                "residual_px": float(e.get("median_residual_px", np.nan)),
                "pred_pct": predicted_along_pct(np.asarray(e.get("inliers_px", []), float), e["median_residual_px"]),
                "tracked": bool(e.get("tracked", False)),
                "R_est": R_e,
                "t_est": t_e,
                "R_gt": R_g,
                "t_gt": t_g,
            }
        )
    return pd.DataFrame(rows)


def sequence_terms(pairs: pd.DataFrame, run: RunData) -> pd.DataFrame:
    """ADD with the along-ray error's per-(video, object) mean removed, and with only that mean left."""
    points, _ = run.model_points(pairs["obj_name"].unique())
    out = pairs.copy()
    mean_pct = pairs.groupby(["video", "obj_name"])["along_pct"].transform("mean")
    out["seq_mean_pct"] = mean_pct
    for col, left_pct in (("add_no_bias_m", pairs["along_pct"] - mean_pct), ("add_no_scatter_m", mean_pct)):
        vals = []
        for r, keep in zip(pairs.to_dict("records"), left_pct, strict=True):
            ray = r["t_gt"] / np.linalg.norm(r["t_gt"])
            t = r["t_est"] - r["along_m"] * ray + keep / 100.0 * r["z_m"] * ray
            vals.append(add(r["R_est"], t, r["R_gt"], r["t_gt"], points[r["obj_name"]]))
        out[col] = vals
    return out


def camera_travel(run: RunData) -> str:
    """Per video: how far the camera moves over its frames (the largest distance between two of its positions,
    taken in the ground-truth frame of the object seen in the most frames) against its distance to it."""
    lines = []
    gt = run.gt.assign(video=run.gt["frame_id"].map(video_of))
    for video, g in gt.groupby("video"):
        rows = g[g["obj_name"] == g["obj_name"].value_counts().index[0]]
        if len(rows) < 2:
            continue
        centres = np.array([-R.T @ t for R, t in map(_rt, rows.to_dict("records"))])
        travel = max(np.linalg.norm(centres - c, axis=1).max() for c in centres)
        dist = np.median(np.linalg.norm(centres, axis=1))
        pct = 100 * travel / dist
        lines.append(f"  {video}: {len(rows)} frames, {1000 * travel:.0f} mm at {dist:.2f} m ({pct:.1f} %)")
    return "\n".join(lines)


def camera_elevation(run: RunData) -> str:
    """Per video: the camera's elevation above the table (degrees, min–max over its frames and objects), the
    table being the plane the ground-truth poses rest on (the plane search's own rule)."""
    from batchpose.config import PlaneConfig  # noqa: PLC0415
    from batchpose.method.support import one_object_plane, resting_faces, stable_faces, support_plane  # noqa: PLC0415

    conf = PlaneConfig()
    meshes = {n: load_mesh(Path(o["mesh"]), run.mesh_conf, name=n).mesh for n, o in run.objects.items()}
    hulls = {n: m.convex_hull for n, m in meshes.items()}
    stable = {n: stable_faces(m) for n, m in meshes.items()}
    downs = {n: st[0] for n, st in stable.items()}
    gt = run.gt.assign(video=run.gt["frame_id"].map(video_of))
    lines = []
    for video, g in gt.groupby("video"):
        angles = []
        for _, rows in g[g["obj_name"].isin(meshes)].groupby("frame_id"):
            poses = {}
            for r in rows.to_dict("records"):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = _rt(r)
                poses[r["obj_name"]] = T
            plane = support_plane({n: (T, hulls[n]) for n, T in poses.items()}, conf, downs)
            if plane is None and len(poses) == 1:
                ((n, T),) = poses.items()
                plane = one_object_plane(n, T, hulls[n], resting_faces(stable[n], conf.min_stable), conf)
            if plane is None:
                continue
            for n in plane.objects:
                c = poses[n][:3, :3] @ hulls[n].centroid + poses[n][:3, 3]
                angles.append(np.degrees(np.arcsin(-(plane.normal @ c) / np.linalg.norm(c))))
        if angles:
            lines.append(f"  {video}: {len(angles)} objects on the table, {min(angles):.0f}–{max(angles):.0f}°")
    return "\n".join(lines)


def _silhouette_median(rendered: np.ndarray, sensor: np.ndarray, inside: np.ndarray) -> float:
    """Median rendered-minus-sensor depth (m) on ``inside`` pixels both have, within :data:`DEPTH_GATE_M`."""
    diff = rendered - sensor
    sel = inside & (sensor > 0) & (np.abs(diff) < DEPTH_GATE_M)
    return float(np.median(diff[sel])) if sel.sum() >= 50 else float("nan")


def depth_terms(pairs: pd.DataFrame, run: RunData) -> pd.DataFrame:
    """The mesh rendered at the ground truth and at the estimate against the frame's depth image.

    Adds ``gt_depth_mm`` / ``est_depth_mm`` (median rendered minus measured inside the ground truth's
    silhouette less its rim, mm; NaN without depth or with under 50 such pixels) and ``gt_depth_pct``.
    """
    import cv2

    wanted = set(pairs["frame_id"])
    meshes = {
        n: load_mesh(Path(o["mesh"]), run.mesh_conf, name=n) for n, o in run.objects.items() if n in set(pairs.obj_name)
    }
    renderer = get_renderer()
    kernel = np.ones((2 * RIM_PX + 1, 2 * RIM_PX + 1), np.uint8)
    found: dict[tuple[str, str], tuple[float, ...]] = {}
    by_frame = {f: g for f, g in pairs.groupby("frame_id")}
    for frame in open_frames((run.manifest or {})["frames"], run.run_dir):
        if frame.frame_id not in wanted:
            continue
        depth = decode_depth(frame)
        if depth is None:
            continue
        K, w, h = frame.camera.K, frame.camera.width, frame.camera.height
        gray = cv2.cvtColor(decode_image(frame), cv2.COLOR_RGB2GRAY)
        for r in by_frame[frame.frame_id].to_dict("records"):
            m = meshes[r["obj_name"]]
            shots = []
            for R, t in ((r["R_gt"], r["t_gt"]), (r["R_est"], r["t_est"])):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R, t
                shots.append(renderer.render(m.content_hash, m.mesh, T, K, w, h, "flat", 0.05, 10.0))
            silhouette = (shots[0][1] > 0).astype(np.uint8)
            inside = cv2.erode(silhouette, kernel).astype(bool)
            near = cv2.dilate(silhouette, kernel).astype(bool)
            scale, _ = image_scale(gray, cv2.cvtColor(shots[0][0], cv2.COLOR_RGB2GRAY), near)
            found[(r["frame_id"], r["obj_name"])] = (
                _silhouette_median(shots[0][1], depth, inside),
                _silhouette_median(shots[1][1], depth, inside),
                scale,
            )
    out = pairs.copy()
    keys = list(zip(pairs["frame_id"], pairs["obj_name"], strict=True))
    none = (np.nan,) * 3
    out["gt_depth_mm"] = [1000 * found.get(k, none)[0] for k in keys]
    out["est_depth_mm"] = [1000 * found.get(k, none)[1] for k in keys]
    # the along-ray error the image's own scale implies: the object looks like the mesh that much farther
    out["image_pct"] = [100 * (1 / found.get(k, none)[2] - 1) for k in keys]
    out["gt_depth_pct"] = out["gt_depth_mm"] / (10 * out["z_m"])
    return out


def image_scale(real_gray: np.ndarray, render_gray: np.ndarray, mask: np.ndarray) -> tuple[float, int]:
    """The image scale of the real object against the mesh rendered at the ground truth.

    SIFT keypoints of both images inside ``mask`` are matched (Lowe's ratio 0.8) and a similarity fitted by
    RANSAC (3 px); its scale is the real object's image size over the render's: 1 when image, mesh, camera
    and ground truth agree, ``1 / (1 + e)`` when the real object looks like the mesh ``e`` farther away.

    Args:
        real_gray, render_gray: (H, W) uint8 images.
        mask: (H, W) bool, where to look (the rendered silhouette, dilated).

    Returns:
        (scale, inliers); (NaN, 0) with under 12 inliers.
    """
    import cv2

    sift = cv2.SIFT_create()
    m8 = mask.astype(np.uint8) * 255
    k1, d1 = sift.detectAndCompute(real_gray, m8)
    k2, d2 = sift.detectAndCompute(render_gray, m8)
    if d1 is None or d2 is None or len(k1) < 12 or len(k2) < 12:
        return float("nan"), 0
    pairs = cv2.BFMatcher().knnMatch(d2, d1, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
    if len(good) < 12:
        return float("nan"), 0
    src = np.float32([k2[g.queryIdx].pt for g in good])
    dst = np.float32([k1[g.trainIdx].pt for g in good])
    A, inl = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=3.0)
    n = int(inl.sum()) if inl is not None else 0
    if A is None or n < 12:
        return float("nan"), n
    return float(np.sqrt(abs(np.linalg.det(A[:, :2])))), n


def _f(x: float, fmt: str = "+.1f") -> str:
    return "-" if not np.isfinite(x) else format(x, fmt)


def _pass_pct(d: pd.Series, diam: pd.Series) -> str:
    return f"{100 * float((d < 0.1 * diam).mean()):.0f} %"


def split_table(pairs: pd.DataFrame, key: str) -> str:
    """Per ``key`` (obj_name or video): the error split of the right poses, medians."""
    rows = []
    for name, g in list(pairs.groupby(key)) + [("all", pairs)]:
        rows.append(
            [
                name,
                len(g),
                _f(g["z_m"].median(), ".2f"),
                _f(g["rot_deg"].median(), ".1f"),
                _f(1000 * g["along_m"].median()),
                _f(g["along_pct"].median(), "+.2f"),
                _f(g["along_pct"].quantile(0.25), "+.2f") + " … " + _f(g["along_pct"].quantile(0.75), "+.2f"),
                _f(1000 * g["across_m"].median(), ".1f"),
                _f(g["ratio"].median(), ".4f"),
                _pass_pct(g["add_m"], g["diameter_m"]),
                _pass_pct(g["add_no_along_m"], g["diameter_m"]),
            ]
        )
    cols = [key, "n", "z m", "rot °", "along mm", "along %", "along % IQR", "across mm", "|t|/|t_gt|"]
    return table(rows, cols + ["ADD<0.1d", "no along"])


def cause_table(pairs: pd.DataFrame) -> str:
    """Per (video, object): depth consistency of the ground truth and of the estimate; SIFT's prediction."""
    rows = []
    for (video, name), g in pairs.groupby(["video", "obj_name"]):
        meas = g["along_pct"]
        rows.append(
            [
                video,
                name,
                len(g),
                _f(g["gt_depth_mm"].median()) if "gt_depth_mm" in g else "-",
                _f(g["gt_depth_pct"].median(), "+.2f") if "gt_depth_pct" in g else "-",
                _f(g["est_depth_mm"].median()) if "est_depth_mm" in g else "-",
                _f(g["image_pct"].median(), "+.2f") if "image_pct" in g else "-",
                _f(meas.mean(), "+.2f"),
                _f(meas.std(ddof=1), ".2f") if len(g) > 1 else "-",
                _f(1000 * g["along_m"].median()),
                _f(g["pred_pct"].median(), ".2f"),
                f"{g['n_inliers'].median():.0f}",
                _f(g["residual_px"].median(), ".2f"),
                f"{(np.sign(meas) == np.sign(meas.mean())).mean() * 100:.0f} %",
                _pass_pct(g["add_m"], g["diameter_m"]) + " → " + _pass_pct(g["add_no_along_m"], g["diameter_m"]),
            ]
        )
    cols = [
        "video",
        "object",
        "n",
        "GT-depth mm",
        "GT-depth %",
        "est-depth mm",
        "image %",
        "along % mean",
        "along % sd",
        "along mm",
    ]
    return table(rows, cols + ["SIFT pred. sd %", "inliers", "resid. px", "same sign", "ADD<0.1d → no along"])


def pinning_table(pairs: pd.DataFrame) -> str:
    """ADD < 0.1 d of the right poses: as is, along-ray error removed, its sequence mean / scatter removed."""
    rows = []
    for name, g in list(pairs.groupby("obj_name")) + [("all", pairs)]:
        d = g["diameter_m"]
        fails = g["add_m"] >= 0.1 * d
        rescued = int((fails & (g["add_no_along_m"] < 0.1 * d)).sum())
        rows.append(
            [
                name,
                len(g),
                _pass_pct(g["add_m"], d),
                _pass_pct(g["add_no_along_m"], d),
                _pass_pct(g["add_no_bias_m"], d),
                _pass_pct(g["add_no_scatter_m"], d),
                f"{rescued} of {int(fails.sum())}",
            ]
        )
    cols = ["object", "n", "as is", "no along-ray error", "sequence mean removed", "scatter removed"]
    return table(rows, cols + ["ADD failures rescued"])


def side_by_side(runs: dict[str, pd.DataFrame]) -> str:
    """Per object, on the (frame, object) pairs right in every run: median along-ray mm and across mm."""
    keys = None
    for p in runs.values():
        k = set(zip(p["frame_id"], p["obj_name"], strict=True))
        keys = k if keys is None else keys & k
    rows = []
    names = sorted({n for _, n in keys or set()}) + ["all"]
    for name in names:
        row: list[object] = [name]
        for p in runs.values():
            sel = [(f, o) in keys and (name in ("all", o)) for f, o in zip(p["frame_id"], p["obj_name"], strict=True)]
            g = p[sel]
            row += [
                len(g),
                _f(1000 * g["along_m"].median()),
                _f(1000 * g["across_m"].median(), ".1f"),
                _f(g["rot_deg"].median(), ".1f"),
            ]
        rows.append(row)
    cols = ["object"] + [f"{label}: {c}" for label in runs for c in ("n", "along mm", "across mm", "rot °")]
    return table(rows, cols)


def study(run_dir: Path, max_rot_deg: float, with_depth: bool) -> pd.DataFrame:
    """Print one run's tables; return its right poses' rows (for the side-by-side table)."""
    run = load_run(run_dir)
    if not run.has_gt:
        sys.exit(f"{run_dir}: no ground truth (gt.parquet): nothing to measure against")
    every = pair_table(run)
    pairs = every[every["rot_deg"] < max_rot_deg].reset_index(drop=True)
    right = f"{len(pairs)} of {len(every)} ok poses within {max_rot_deg:g}° of the ground truth's rotation"
    print(f"\n## {run_dir} — {right}")
    if pairs.empty:
        return pairs
    pairs = sequence_terms(pairs, run)
    if with_depth:
        pairs = depth_terms(pairs, run)
    print("\nthe error split per object (medians; along: + is too far)\n" + split_table(pairs, "obj_name"))
    print("\nper video\n" + split_table(pairs, "video"))
    print("\nthe causes per video and object: rendered minus sensor depth inside the GT silhouette (median),")
    print("the along-ray error over the sequence (mean, sd; median mm) and the sd SIFT's inliers predict")
    print(cause_table(pairs))
    print("\nADD < 0.1 d of the right poses\n" + pinning_table(pairs))
    print("\nthe camera's travel over each video's frames (what a static object's frames can triangulate)")
    print(camera_travel(run))
    print("the camera's elevation above the table (the plane the ground-truth poses rest on)")
    print(camera_elevation(run))
    wrong = every[every["rot_deg"] >= max_rot_deg]
    fails = every["add_m"] >= 0.1 * every["diameter_m"]
    rescued = fails & (every["add_no_along_m"] < 0.1 * every["diameter_m"])
    print(
        f"all ok poses: {int(fails.sum())} of {len(every)} fail ADD < 0.1 d; {int(rescued.sum())} pass with the "
        f"along-ray error removed; {len(wrong)} have the rotation wrong"
    )
    return pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dirs", type=Path, nargs="+")
    ap.add_argument("--max-rot-deg", type=float, default=10.0, help="a right pose's largest rotation error")
    ap.add_argument("--no-depth", action="store_true", help="skip the comparison with the depth images")
    args = ap.parse_args()
    print(f"machine : {machine()}\ncode    : {code_version()}")
    runs = {p.name: study(p, args.max_rot_deg, not args.no_depth) for p in args.run_dirs}
    if len(runs) > 1:
        print("\nside by side, on the (frame, object) pairs every run got right (medians)\n" + side_by_side(runs))


if __name__ == "__main__":
    main()

"""The overlay gallery: model points and 3D bounding box drawn at the estimated (and ground-truth) pose on
the frame, cropped around the object, for the worst, failed and best cases (or the least and most confident
without ground truth). Each case is a JPEG thumbnail and a full-size JPEG (base64), picked to spread over the
objects and frames: each object's worst first, then frames not shown yet."""

from __future__ import annotations

import base64
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import pandas as pd

from batchpose.core.poses import row_cam_from_model
from batchpose.errors import BatchposeError, DataError
from batchpose.report.runs import RunData, fetch_frames
from batchpose.report.scoring import status_label

#: Most cases of each gallery group (a run's worst, failed and best; least and most confident without
#: ground truth).
GROUP_SIZES = {"worst": 6, "failed": 4, "best": 3, "least confident": 6, "most confident": 3}
#: Height of a gallery thumbnail, pixels.
THUMB_HEIGHT = 240
#: Smallest height of the full-size overlay, pixels (a crop smaller than this is enlarged).
FULL_MIN_HEIGHT = 480
#: JPEG quality of the overlays (0-100).
JPEG_QUALITY = 88
COLOR_EST = (255, 140, 0)  # RGB orange
COLOR_GT = (40, 200, 60)  # RGB green

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


def _crop_window(uv: np.ndarray, w: int, h: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) pixel window around the drawn (N, 2) points, with context; the whole frame when
    nothing lands near it."""
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    uv = uv[(uv[:, 0] > -w) & (uv[:, 0] < 2 * w) & (uv[:, 1] > -h) & (uv[:, 1] < 2 * h)]
    if not len(uv):
        return 0, 0, w, h
    (ux0, uy0), (ux1, uy1) = uv.min(axis=0), uv.max(axis=0)
    # A 4:3 window around the drawing, shifted (not clipped) to stay inside the frame, so every
    # thumbnail has the same shape.
    ch = min(float(h), max(ux1 - ux0, uy1 - uy0, 40.0) * 1.6)
    cw = min(float(w), ch * 4 / 3)
    cx = min(max((ux0 + ux1) / 2, cw / 2), w - cw / 2)
    cy = min(max((uy0 + uy1) / 2, ch / 2), h - ch / 2)
    return round(cx - cw / 2), round(cy - ch / 2), round(cx + cw / 2), round(cy + ch / 2)


def draw_overlay(
    rgb: np.ndarray,
    K: np.ndarray,
    pts: np.ndarray,
    poses: list[tuple[np.ndarray, tuple[int, int, int]]],
    dist: np.ndarray | None = None,
    out_height: int | None = THUMB_HEIGHT,
) -> np.ndarray:
    """Draw model points and their 3D bounding box at each pose, cropped around the object.

    Args:
        rgb: (H, W, 3) uint8 RGB frame.
        K: (3, 3) intrinsics.
        pts: (N, 3) model points, metres.
        poses: (4x4 cam_from_model, RGB colour) pairs, drawn in order (last on top).
        dist: OpenCV distortion coefficients (empty or None: none).
        out_height: height of the returned image in pixels; None: the crop at the frame's own resolution, but
            at least :data:`FULL_MIN_HEIGHT` pixels high.

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
    x0, y0, x1, y1 = _crop_window(all_uv, w, h)
    if out_height is None:
        out_height = max(y1 - y0, FULL_MIN_HEIGHT)
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


def _jpeg_b64(rgb: np.ndarray) -> str:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise DataError("cannot encode overlay JPEG")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def spread(rows: pd.DataFrame, k: int) -> pd.DataFrame:
    """Up to ``k`` of ``rows`` (frame_id, obj_name; in order of preference) spread over objects and frames:
    each object's first row, then rows of frames not shown yet, then the rest, each pass in ``rows``' order."""
    picked: list = []
    objects: set[str] = set()
    frames: set[str] = set()
    for rule in ("object", "frame", "any"):
        for i, r in zip(rows.index, rows.itertuples(index=False), strict=True):
            if len(picked) == k:
                return rows.loc[picked]
            new_object = r.obj_name not in objects
            if i in picked or (rule == "object" and not new_object) or (rule == "frame" and r.frame_id in frames):
                continue
            picked.append(i)
            objects.add(r.obj_name)
            frames.add(r.frame_id)
    return rows.loc[picked]


@dataclass
class _Case:
    group: str
    frame_id: str
    obj_name: str
    caption: str
    est: np.ndarray | None
    gt: np.ndarray | None


def _best_estimates(poses: pd.DataFrame) -> dict[tuple[str, str], tuple[np.ndarray | None, dict[str, Any]]]:
    """(frame_id, obj_name) -> (cam_from_model or None, row): the first ok row of each pair, else its first row."""
    est_by_key: dict[tuple[str, str], tuple[np.ndarray | None, dict[str, Any]]] = {}
    for r in poses.to_dict("records"):
        T = row_cam_from_model(r) if r["status"] == "ok" else None
        key = (r["frame_id"], r["obj_name"])
        if key not in est_by_key or (T is not None and est_by_key[key][0] is None):
            est_by_key[key] = (T, r)
    return est_by_key


def _worse_half(ranked: pd.DataFrame) -> pd.DataFrame:
    """The first half of ``ranked`` rows (worst first) and each object's first row, in ``ranked``'s order:
    the candidates of the worst group, where every object shows its worst case."""
    head = ranked.index[: max(1, (len(ranked) + 1) // 2)]
    each = ranked.drop_duplicates("obj_name").index
    return ranked[ranked.index.isin(head) | ranked.index.isin(each)]


def _gt_cases(run: RunData, per_instance: pd.DataFrame) -> list[_Case]:
    """The worst (by ADD-S), failed and best instances, each with its ground-truth pose."""
    est_by_key = _best_estimates(run.poses)
    assert run.gt is not None  # only runs with ground truth have these cases
    gt_by_key = {(r["frame_id"], r["obj_name"]): r for r in run.gt.to_dict("records")}
    ok = per_instance[(per_instance["status"] == "ok") & np.isfinite(per_instance["adds_m"])]
    ok = ok.sort_values("adds_m", ascending=False, kind="stable")
    worst = spread(_worse_half(ok), GROUP_SIZES["worst"])
    best = spread(ok.drop(worst.index).iloc[::-1], GROUP_SIZES["best"])
    failed = spread(per_instance[per_instance["status"] != "ok"], GROUP_SIZES["failed"])
    cases = []
    for group, rows in (("worst", worst), ("failed", failed), ("best", best)):
        for r in rows.to_dict("records"):
            key = (r["frame_id"], r["obj_name"])
            g = gt_by_key[key]
            T_gt = np.eye(4)
            T_gt[:3, :3] = np.asarray(g["R"], dtype=float).reshape(3, 3)
            T_gt[:3, 3] = np.asarray(g["t_m"], dtype=float).reshape(3)
            est = est_by_key.get(key, (None, {}))
            if group == "failed":
                reason = est[1].get("reason", "") if est[1] else ""
                caption = status_label(r["status"]) + (f": {reason}" if reason else "") + " (ground truth only)"
            else:
                wrong = " > 0.1 d: wrong" if r["adds_m"] > 0.1 * r["diameter_m"] else ""
                caption = (
                    f"ADD-S {r['adds_m'] * 1000:.1f} mm{wrong}, ADD {r['add_m'] * 1000:.1f} mm, "
                    f"rot {r['rot_err_deg']:.1f}°, conf {r['confidence']:.2f}"
                )
            cases.append(_Case(group, key[0], key[1], caption, est[0], T_gt))
    return cases


def _confidence_cases(poses: pd.DataFrame) -> list[_Case]:
    """The least and most confident ok estimates (a run without ground truth)."""
    ok = poses[poses["status"] == "ok"].sort_values("confidence", kind="stable")
    low = spread(_worse_half(ok), GROUP_SIZES["least confident"])
    top = spread(ok.drop(low.index).iloc[::-1], GROUP_SIZES["most confident"])
    cases = []
    for group, rows in (("least confident", low), ("most confident", top)):
        for r in rows.to_dict("records"):
            caption = f"confidence {r['confidence']:.2f}, {int(r.get('n_inliers', 0))} inliers"
            cases.append(_Case(group, r["frame_id"], r["obj_name"], caption, row_cam_from_model(r), None))
    return cases


def gallery(run: RunData, per_instance: pd.DataFrame | None) -> tuple[list[dict[str, str]], str]:
    """Overlay images as dicts (id, group, title, caption; ``thumb`` and ``full``: base64 JPEG) and a note
    explaining any gap.

    Args:
        run: the loaded run (its manifest's ``frames:`` source is read for the frames shown).
        per_instance: per-instance errors (:func:`batchpose.report.scoring.score_run`); None without ground truth.
    """
    cases = _gt_cases(run, per_instance) if per_instance is not None else _confidence_cases(run.poses)
    if not cases:
        return [], "no estimates to show"
    names = {c.obj_name for c in cases}
    try:
        points, _ = run.model_points(names)
    except BatchposeError as e:
        return [], f"no model points to draw ({e})"
    frames, note = fetch_frames(run, {c.frame_id for c in cases})
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
        K, dist, pts = np.asarray(frame.camera.K, float), np.asarray(frame.camera.dist, float), points[case.obj_name]
        thumb = draw_overlay(rgb, K, pts, draw, dist=dist)
        full = draw_overlay(rgb, K, pts, draw, dist=dist, out_height=None)
        counters[case.group] = counters.get(case.group, 0) + 1
        slug = case.group.replace(" ", "-")
        items.append(
            {
                "id": f"overlay-{slug}-{counters[case.group]}",
                "group": case.group,
                "title": f"{case.frame_id} · {case.obj_name}",
                "caption": case.caption,
                "thumb": _jpeg_b64(thumb),
                "full": _jpeg_b64(full),
            }
        )
    if problems:
        note = "; ".join(filter(None, [note, f"{len(problems)} frames could not be decoded ({problems[0]})"]))
    return items, note

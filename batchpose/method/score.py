"""The verification score (``min_verification``, :func:`verify_poses`): the mesh rendered at a pose, compared
with the frame, as one number a user can read — the estimated probability that the pose is on the object.

Three comparisons of the render with the frame, each blind to how the pose was found (first pass, retry,
search), over the object's pixels that no other reported pose hides:

- **outline**: how much better the render's outline meets the frame's edges at the pose than beside it. An
  outline pixel is met when the frame has an edge of about its orientation (LINE-2D's gradient orientations,
  :data:`N_ORIENTATIONS` bins over a half turn, one bin either way, spread :data:`SPREAD_PX` px) there; the
  share met at the pose, ``s``, is compared with the mean share met with the outline moved
  :data:`SHIFT_PX` px eight ways, ``b``: ``(s - b) / (1 - b)``. A right pose's outline meets edges where it
  is and fewer beside it; a pose laid over clutter meets as many everywhere.
- **gradient**: :func:`batchpose.method.appearance.gradient_match` of the render's and the frame's Sobel
  gradients over the silhouette.
- **texture**: :func:`batchpose.method.appearance.texture_match` (Lab correlation), as ``verify_below``'s.

The score is a logistic function of the three (:data:`WEIGHTS`, fitted by ``benchmarks/verification.py``
on synthetic held-out frames, never on the real frames it is measured on), so 0.5 means about even odds on
the frames it was fitted on. ``poses.parquet`` holds it as ``verification`` for every pose it scored; tracked
poses are not scored (the tracker checks them frame to frame) and hold NaN.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import cv2
import numpy as np

from batchpose.core.frames import Frame
from batchpose.core.poses import PoseRecord
from batchpose.method.appearance import gradient_match, texture_match
from batchpose.method.objects import Objects
from batchpose.method.records import pose_of
from batchpose.method.sequence import Sequence
from batchpose.method.verify import VERIFY_MIN_PX, hidden_by

#: Gradient orientation bins over a half turn (an edge's sign is not compared).
N_ORIENTATIONS = 8
#: A frame pixel is an edge when its Sobel gradient (3x3, after a 3x3 Gaussian) is at least this strong.
EDGE_STRENGTH = 40.0
#: Each frame edge is spread this many pixels, so an outline a pixel or two off still meets it.
SPREAD_PX = 2
#: The outline is also tried this far off (eight ways) for the chance of meeting edges there.
SHIFT_PX = 8
_SHIFTS = [(SHIFT_PX, 0), (-SHIFT_PX, 0), (0, SHIFT_PX), (0, -SHIFT_PX)] + [
    (a * SHIFT_PX * 3 // 4, b * SHIFT_PX * 3 // 4) for a in (1, -1) for b in (1, -1)
]
#: Fewer outline pixels than this in view (off the image, hidden by other poses): no outline term (0).
MIN_OUTLINE_PX = 20
#: The comparison's box reaches this far beyond the render, for its filters' support.
_MARGIN_PX = 6
#: Logistic weights of (1, outline, gradient, texture); see ``benchmarks/verification.py``.
WEIGHTS = (-5.99, 3.11, 11.83, 4.32)


@dataclass(frozen=True)
class Comparison:
    """The render-and-compare terms of one pose (see the module docstring)."""

    outline: float
    gradient: float
    texture: float

    def score(self) -> float:
        """The verification score in (0, 1)."""
        w = WEIGHTS
        z = w[0] + w[1] * self.outline + w[2] * self.gradient + w[3] * self.texture
        return float(1.0 / (1.0 + np.exp(-z)))


class FrameEdges:
    """The frame as the comparisons see it, made once per frame: its gray and Lab images, and its edges by
    orientation, spread (one bit per orientation bin; made on first use, as a texture match alone needs
    only the Lab image)."""

    def __init__(self, rgb: np.ndarray) -> None:
        self.gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        self.lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB)

    @functools.cached_property
    def spread(self) -> np.ndarray:
        """(H, W) uint8: bit i set where a frame edge of orientation bin i lies within :data:`SPREAD_PX`."""
        bins, strong = orientations(self.gray, EDGE_STRENGTH)
        bits = np.where(strong, np.left_shift(1, bins), 0).astype(np.uint8)
        kernel = np.ones((2 * SPREAD_PX + 1, 2 * SPREAD_PX + 1), np.uint8)
        spread = np.zeros_like(bits)
        for i in range(N_ORIENTATIONS):
            spread |= cv2.dilate((bits >> i) & 1, kernel) << i
        return spread

    def met(self, ys: np.ndarray, xs: np.ndarray, bins: np.ndarray, dy: int = 0, dx: int = 0) -> float:
        """The share of outline pixels (ys, xs) with orientation ``bins`` that meet a frame edge of about that
        orientation when moved by (dy, dx); of those still on the image."""
        h, w = self.spread.shape
        y, x = ys + dy, xs + dx
        inside = (y >= 0) & (y < h) & (x >= 0) & (x < w)
        if not inside.any():
            return 0.0
        b = bins[inside]
        want = sum(np.left_shift(1, (b + k) % N_ORIENTATIONS) for k in (-1, 0, 1)).astype(np.uint8)
        return float(((self.spread[y[inside], x[inside]] & want) > 0).mean())


def orientations(gray: np.ndarray, strength: float) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's gradient orientation bin (of :data:`N_ORIENTATIONS` over a half turn) and whether its
    gradient is at least ``strength`` strong."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (3, 3), 0)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    angle = cv2.phase(gx, gy)  # [0, 2 pi)
    bins = (angle * (N_ORIENTATIONS / np.pi)).astype(np.int64) % N_ORIENTATIONS
    return bins, cv2.magnitude(gx, gy) >= strength


def compare(edges: FrameEdges, rendered_rgb: np.ndarray, depth: np.ndarray, seen: np.ndarray) -> Comparison | None:
    """The render (``rendered_rgb``, ``depth``) against the frame over the pixels ``seen`` (the render's, less
    what other poses hide); None under :data:`VERIFY_MIN_PX` such pixels. Computed in the render's bounding
    box (and a margin the filters need)."""
    if seen.sum() < VERIFY_MIN_PX:
        return None
    ys, xs = np.nonzero(depth > 0)
    m = _MARGIN_PX
    y0, x0 = max(int(ys.min()) - m, 0), max(int(xs.min()) - m, 0)
    box = np.s_[y0 : int(ys.max()) + m + 1, x0 : int(xs.max()) + m + 1]
    mask, seen, rgb = (depth[box] > 0).astype(np.uint8), seen[box], rendered_rgb[box]
    outline = (mask > 0) & (cv2.erode(mask, np.ones((3, 3), np.uint8)) == 0) & seen
    ys, xs = np.nonzero(outline)
    term = 0.0
    if len(ys) >= MIN_OUTLINE_PX:
        bins, _ = orientations(cv2.GaussianBlur(mask.astype(np.float32) * 255.0, (5, 5), 0), 0.0)
        b = bins[ys, xs]
        ys, xs = ys + y0, xs + x0
        at = edges.met(ys, xs, b)
        beside = float(np.mean([edges.met(ys, xs, b, dy, dx) for dy, dx in _SHIFTS]))
        term = (at - beside) / max(1.0 - beside, 0.05)
    near = cv2.dilate(seen.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return Comparison(
        float(np.clip(term, -1.0, 1.0)),
        gradient_match(edges.gray[box], cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), near),
        texture_match(edges.lab[box][seen], rgb[seen]),
    )


def verify_poses(
    objects: Objects,
    frame: Frame,
    rgb: np.ndarray,
    records: list[PoseRecord],
    sequence: Sequence,
    checked: dict[int, np.ndarray] | None = None,
) -> None:
    """``min_verification``: score every untracked ok pose (and the low-confidence ones, for the report's
    curve); an ok pose scoring under the threshold becomes low_confidence and leaves the sequence's tracks,
    one under ``track_verification`` starts no track (neither in a frame the depth step checks:
    ``depth.enabled`` and a depth image).
    Run after the estimate and again after the searches: ``checked`` (id(record) -> the pose it was scored
    at, kept between the two) skips the poses scored already."""
    checked = {} if checked is None else checked
    conf = objects.conf
    # With a depth image the depth step checks every pose against the sensor; the score, fitted on RGB poses,
    # is recorded but does not reject: colour and depth can disagree in scale (1-4.5 % on YCB-Video), and a
    # pose aligned to the depth then renders a little larger than the colour image shows it.
    judged_by_depth = conf.depth.enabled and frame.has_depth
    scored = [
        r for r in records
        if r.status in ("ok", "low_confidence") and not r.tracked and r.cam_from_model is not None
        and checked.get(id(r)) is not r.cam_from_model and r.obj_name in objects.models
    ]  # fmt: skip
    if objects.renderer is None or not scored:
        return
    t0 = time.perf_counter()
    found = comparisons(objects, frame, rgb, records, scored)
    each = (time.perf_counter() - t0) / len(scored)
    for rec in scored:
        c = found[id(rec)]
        rec.verification = c.score() if c is not None else 0.0
        checked[id(rec)] = pose_of(rec)
        rec.timings["verify"] = rec.timings.get("verify", 0.0) + each
        if not rec.ok or judged_by_depth:
            continue
        if rec.verification < conf.track_verification:
            sequence.tracks.pop(rec.obj_name, None)  # a fresh pose's track is the one it started
        if rec.verification < conf.min_verification:
            rec.status = "low_confidence"
            what = (
                f"outline {c.outline:.2f}, gradient {c.gradient:.2f}, texture {c.texture:.2f}"
                if c is not None
                else f"under {VERIFY_MIN_PX} px of it in view"
            )
            rec.reason = (
                f"{rec.reason + '; ' if rec.reason else ''}verification {rec.verification:.2f} < "
                f"min_verification {conf.min_verification:g} ({what})"
            )
            sequence.drop(rec)


def comparisons(
    objects: Objects, frame: Frame, rgb: np.ndarray, records: list[PoseRecord], targets: list[PoseRecord]
) -> dict[int, Comparison | None]:
    """id(record) -> :func:`compare` of each of ``targets`` (records with a pose) with the frame ``rgb``, over
    the pixels the frame's other ok poses among ``records`` do not hide (rendered only where their image boxes
    meet the target's)."""
    cam = frame.camera
    boxes = {id(r): _box(objects, r, cam) for r in records if r.ok and r.obj_name in objects.models}
    boxes.update({id(r): _box(objects, r, cam) for r in targets})
    shown: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # id(record) -> its render, made when first needed

    def render(r: PoseRecord) -> tuple[np.ndarray, np.ndarray]:
        if id(r) not in shown:
            shown[id(r)] = objects.render(r.obj_name, pose_of(r), cam)
        return shown[id(r)]

    edges = FrameEdges(rgb)
    out: dict[int, Comparison | None] = {}
    for rec in targets:
        ren_rgb, depth = render(rec)
        seen = depth > 0
        for other in records:  # what the frame's other ok poses in front of it hide
            if other.ok and other.obj_name != rec.obj_name and _meet(boxes.get(id(other)), boxes[id(rec)]):
                seen &= ~hidden_by(render(other)[1], depth)
        out[id(rec)] = compare(edges, ren_rgb, depth, seen)
    return out


def _box(objects: Objects, rec: PoseRecord, cam) -> tuple[float, float, float, float] | None:
    """The image box (x0, y0, x1, y1) of the object's convex hull at the record's pose; None when any of it
    is behind the camera (it may cover anything)."""
    T = pose_of(rec)
    p = objects.hull(rec.obj_name) @ T[:3, :3].T + T[:3, 3]
    if np.any(p[:, 2] <= 1e-3):
        return None
    uv = p[:, :2] / p[:, 2:] * np.diag(cam.K)[:2] + cam.K[:2, 2]
    return (*uv.min(axis=0), *uv.max(axis=0))


def _meet(a, b) -> bool:
    """Whether two :func:`_box` boxes overlap (a None box meets every box)."""
    if a is None or b is None:
        return True
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]

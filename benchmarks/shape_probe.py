"""Shape probe (a prototype, not used by the pipeline): can an object SIFT cannot match be found by its edges?

For a low-texture object (the default: the mustard bottle in ycbv_dev's video 0001, which every SIFT pass
misses), renders the library's views at the nearer template distance (every ``--view-step``-th), makes each
view's gradient-magnitude image at ``--scales-per-octave`` image sizes from 48 px to 0.8 of the image's
shorter side and at every 15 degrees in the image plane (at 1/4 resolution: 24,960 templates for the
mustard bottle), and slides them over the frame's gradient-magnitude image with normalised
cross-correlation, ranked by significance atanh(r) * sqrt(n - 3) (n: template pixels; a small template
correlates well anywhere). The best few are refined by half a size and half an angle step, turned into
poses and printed with their ADD-S against the ground truth and a colour score (Bhattacharyya similarity of
the rendered mesh's hue-saturation histogram to the frame's inside the silhouette, minus to a 7-px ring
around it), next to the ground truth's own colour score. With ``--refine N`` the best N hits are refined
by a pattern search on the colour score and the one scoring highest is kept. reports/ACCURACY.md at 8fba8e3,
"Session 7") has the figures and what they say.

Usage:
    .venv/bin/python benchmarks/shape_probe.py [--object 006_mustard_bottle] [--frames 0001/000001 ...]
        [--top 12] [--refine N] [--cache DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO  # noqa: E402  (puts the repo on sys.path)

from batchpose.config import load_estimator_config, load_yaml  # noqa: E402
from batchpose.core.frames import decode_image  # noqa: E402
from batchpose.io import library
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.io.sources import open_frames  # noqa: E402
from batchpose.method.depth_search import pose_from_view  # noqa: E402
from batchpose.method.features import to_gray  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402
from batchpose.stages import build_templates  # noqa: E402

DATA = REPO.parent / "shared" / "data"


@dataclass(frozen=True)
class ShapeConfig:
    level: int = 4
    view_step: int = 2
    angle_step_deg: float = 15.0
    scales_per_octave: int = 4
    min_span_px: float = 48.0
    max_span_fraction: float = 0.8
    margin: float = 0.05


@dataclass
class ShapeHit:
    score: float
    view_id: int
    angle_rad: float
    depth_m: float
    centre_xy: np.ndarray


@dataclass
class _View:
    view_id: int
    crop: np.ndarray  # the rendered view's gray crop (object plus margin)
    centre: np.ndarray  # the model centre's pixel in the crop
    span_px: float  # the object's diameter in the render, pixels


class ShapeBank:
    """Edge templates of one object's views at several sizes and in-plane angles.

    Args:
        render: callable(cam_from_model) -> (rgb, depth) in the library's camera.
        lib: the object's TemplateLibrary (views look at the model centre, which projects to K's centre).
        f_px: the frame camera's focal length; image_size: the frame's (width, height).
        diameter_m: the object's diameter (template sizes run from ``conf.min_span_px`` up to
            ``conf.max_span_fraction`` of the shorter image side).
    """

    def __init__(self, render, lib, f_px: float, image_size: tuple[int, int], diameter_m: float, conf: ShapeConfig):
        self.conf, self.f_px, self.diameter_m = conf, float(f_px), float(diameter_m)
        dist = lib.views["distance_m"].to_numpy()
        f_lib = 0.5 * (lib.K[0, 0] + lib.K[1, 1])
        self.views: list[_View] = []
        for v in np.flatnonzero(np.isclose(dist, dist.min()))[:: conf.view_step]:
            rgb, depth = render(lib.cam_from_model(int(v)))
            if not (depth > 0).any():
                continue
            gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
            ys, xs = np.nonzero(depth > 0)
            span = f_lib * diameter_m / dist[v]
            pad = int(np.ceil(conf.margin * span))
            x0, y0 = max(xs.min() - pad, 0), max(ys.min() - pad, 0)
            x1, y1 = min(xs.max() + pad + 1, gray.shape[1]), min(ys.max() + pad + 1, gray.shape[0])
            self.views.append(_View(int(v), gray[y0:y1, x0:x1], lib.K[:2, 2] - np.array([x0, y0]), span))
        spans, s = [], conf.min_span_px
        while s <= conf.max_span_fraction * min(image_size):
            spans.append(s)
            s *= 2 ** (1 / conf.scales_per_octave)
        angles = np.deg2rad(np.arange(0.0, 360.0, conf.angle_step_deg))
        self.templates, self.keys = [], []  # keys: (view index, span px, angle)
        for i in range(len(self.views)):
            for span in spans:
                small, c_small = self._edges(i, span)
                for a in angles:
                    t = self._turned(small, c_small, a)
                    if t is not None:
                        self.templates.append(t)
                        self.keys.append((i, span, float(a)))

    def _edges(self, i: int, span: float):
        """View i's edges with the object ``span`` pixels across in the frame, at 1/level: image and the
        centre's position in it. Computed as the frame's are (at the frame's scale, then reduced)."""
        view, level = self.views[i], self.conf.level
        scale = span / view.span_px
        small = edge_image(cv2.resize(view.crop, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA), level)
        return small, ((view.centre + 0.5) * scale) / level - 0.5

    @staticmethod
    def _turned(small: np.ndarray, c: np.ndarray, angle: float) -> np.ndarray | None:
        size = int(np.ceil(np.hypot(*small.shape))) + 2
        if size < 6:
            return None
        M = cv2.getRotationMatrix2D((float(c[0]), float(c[1])), -np.degrees(angle), 1.0)
        M[:, 2] += (size - 1) / 2 - c
        t = cv2.warpAffine(small, M, (size, size), flags=cv2.INTER_LINEAR)
        return t if t.std() >= 1e-3 else None

    def template(self, i: int, span: float, angle: float) -> np.ndarray | None:
        return self._turned(*self._edges(i, span), angle)

    def hit(self, score: float, key: tuple, place_xy: np.ndarray) -> ShapeHit:
        i, span, angle = key
        level = self.conf.level
        centre = (np.asarray(place_xy, float) + 0.5) * level - 0.5
        return ShapeHit(score, self.views[i].view_id, angle, self.f_px * self.diameter_m / span, centre)


def edge_image(gray: np.ndarray, level: int) -> np.ndarray:
    """Gradient magnitude (normalised by its 99th percentile, clipped at 1) at 1/level resolution, blurred."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
    m = cv2.magnitude(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    m = np.minimum(m / (float(np.percentile(m, 99)) + 1e-6), 1.0)
    if level > 1:
        m = cv2.resize(m, None, fx=1 / level, fy=1 / level, interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(m, (0, 0), 1.0)


def _significance(r: float, n: int) -> float:
    return float(np.arctanh(min(r, 0.999)) * np.sqrt(max(n - 3, 1)))


def _best_place(frame_edges: np.ndarray, t: np.ndarray, around=None, reach: int = 0):
    """(significance, centre xy at 1/level) of template ``t``'s best place, anywhere or within ``reach``
    cells of ``around``; None when it does not fit."""
    h, w = frame_edges.shape
    th, tw = t.shape
    if th >= h or tw >= w:
        return None
    x0 = y0 = 0
    region = frame_edges
    if around is not None:
        cx, cy = np.rint(np.asarray(around) - [(tw - 1) / 2, (th - 1) / 2]).astype(int)
        x0, y0 = max(cx - reach, 0), max(cy - reach, 0)
        x1, y1 = min(cx + reach + tw, w), min(cy + reach + th, h)
        if x1 - x0 < tw or y1 - y0 < th:
            return None
        region = frame_edges[y0:y1, x0:x1]
    r = cv2.matchTemplate(region, t, cv2.TM_CCOEFF_NORMED)
    _, best, _, (x, y) = cv2.minMaxLoc(r)
    return _significance(best, t.size), np.array([x0 + x + (tw - 1) / 2, y0 + y + (th - 1) / 2])


def search(bank: ShapeBank, frame_edges: np.ndarray, top: int, refine: int = 10) -> list[ShapeHit]:
    """The ``top`` best places of the bank's templates, ranked by significance. The ``refine`` best are
    then tried at half a size step and half an angle step either way, near their place."""
    found = []
    for t, key in zip(bank.templates, bank.keys, strict=True):
        best = _best_place(frame_edges, t)
        if best is not None:
            found.append((best[0], key, best[1]))
    found.sort(key=lambda f: -f[0])
    step_s = 2 ** (0.5 / bank.conf.scales_per_octave)
    step_a = np.deg2rad(0.5 * bank.conf.angle_step_deg)
    refined = []
    for score, key, place in found[:refine]:
        i, span, angle = key
        for s in (span / step_s, span, span * step_s):
            for a in (angle - step_a, angle, angle + step_a):
                t = bank.template(i, s, a)
                best = None if t is None else _best_place(frame_edges, t, place, reach=2)
                if best is not None and best[0] > score:
                    score, key, place = best[0], (i, s, a), best[1]
        refined.append((score, key, place))
    refined += found[refine:]
    refined.sort(key=lambda f: -f[0])
    return [bank.hit(score, key, place) for score, key, place in refined[:top]]


def pose_from(lib, hit: ShapeHit, K: np.ndarray) -> np.ndarray:
    """The pose that shows ``hit``'s view turned by its angle in the image, its centre at ``hit.centre_xy``
    and ``hit.depth_m`` away."""
    return pose_from_view(lib, hit.view_id, hit.angle_rad, hit.depth_m, hit.centre_xy, K)


def colour_score(render, rgb: np.ndarray, T: np.ndarray) -> float:
    """Hue-saturation similarity of the mesh rendered at T to the frame inside its silhouette, minus to a
    7-px ring around it (Bhattacharyya coefficients)."""
    col, depth = render(T)
    m = depth > 0
    if m.sum() < 50:
        return float("nan")
    ring = (cv2.dilate(m.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0) & ~m

    def hist(img, mask):
        h = cv2.calcHist(
            [cv2.cvtColor(img, cv2.COLOR_RGB2HSV)], [0, 1], mask.astype(np.uint8), [18, 8], [0, 180, 0, 256]
        )
        return h / max(float(h.sum()), 1e-9)

    r = hist(col, m)
    return float(np.sum(np.sqrt(r * hist(rgb, m))) - np.sum(np.sqrt(r * hist(rgb, ring))))


def refine_colour(render, rgb: np.ndarray, T: np.ndarray, centre_m: np.ndarray, evals: int = 200):
    """Pattern search on the colour score: turn the object about its centre (start 4 degrees a step), move it
    across the ray (6 mm) and along it (3 %), halving the steps when no move helps. (pose, score, renders)"""
    steps = np.array([4.0, 4.0, 4.0, 0.006, 0.006, 0.03])

    def moved(T, d):
        R = cv2.Rodrigues(np.deg2rad(d[:3]))[0] @ T[:3, :3]
        c = T[:3, :3] @ centre_m + T[:3, 3]
        c = c + np.array([d[3], d[4], c[2] * d[5]])
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = R, c - R @ centre_m
        return out

    best, n = colour_score(render, rgb, T), 1
    while n < evals and steps[0] > 0.25:
        improved = False
        for k in range(6):
            for sign in (1.0, -1.0):
                d = np.zeros(6)
                d[k] = sign * steps[k]
                T2 = moved(T, d)
                s2, n = colour_score(render, rgb, T2), n + 1
                if s2 > best:
                    best, T, improved = s2, T2, True
                    break
        if not improved:
            steps = steps / 2
    return T, best, n


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--object", default="006_mustard_bottle")
    ap.add_argument("--frames", nargs="+", default=["0001/000001", "0001/000003", "0001/000005"])
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--view-step", type=int, default=2)
    ap.add_argument("--scales-per-octave", type=int, default=4)
    ap.add_argument("--cache", default=str(library.default_cache_dir()))
    ap.add_argument(
        "--refine", type=int, default=0, help="refine the best N hits by their colour score and keep the best"
    )
    args = ap.parse_args()
    if not (DATA / "ycbv_dev").is_dir():
        print(f"needs {DATA / 'ycbv_dev'}")
        return 0
    conf = load_estimator_config(load_yaml(REPO / "pipelines" / "gnc_pose.yaml"))
    frames = {
        f.frame_id: f
        for f in open_frames({"format": "ycbv", "root": str(DATA / "ycbv_dev")}, REPO)
        if f.frame_id in set(args.frames)
    }
    first = frames[args.frames[0]]
    model = load_mesh(DATA / "ycb_models" / args.object / "textured.obj", conf.mesh, name=args.object)
    lib = library.load(
        build_templates.build_library(
            model, conf, first.camera.K, first.camera.width, first.camera.height, Path(args.cache)
        )
    )
    renderer = get_renderer()
    pts = lib.pts3d.astype(np.float64)

    def render_in(K, w, h):
        return lambda T: renderer.render(model.content_hash, model.mesh, T, K, w, h, "flat")

    sc = ShapeConfig(view_step=args.view_step, scales_per_octave=args.scales_per_octave)
    cam = first.camera
    t0 = time.perf_counter()
    bank = ShapeBank(
        render_in(lib.K, lib.width, lib.height),
        lib,
        0.5 * (cam.K[0, 0] + cam.K[1, 1]),
        (cam.width, cam.height),
        model.diameter_m,
        sc,
    )
    print(f"{args.object}: {len(bank.templates)} edge templates in {time.perf_counter() - t0:.1f} s")
    for fid in args.frames:
        f = frames[fid]
        rgb, cam = decode_image(f), f.camera
        gts = [p.cam_from_model for p in f.gt if p.obj_name == args.object]
        if not gts:
            print(f"{fid}: {args.object} not annotated")
            continue
        gt, render = gts[0], render_in(cam.K, cam.width, cam.height)
        t0 = time.perf_counter()
        hits = search(bank, edge_image(to_gray(rgb), sc.level), args.top)
        g = pts @ gt[:3, :3].T + gt[:3, 3]
        print(
            f"{fid}: search {time.perf_counter() - t0:.1f} s; ground truth: depth {gt[2, 3]:.2f} m, "
            f"colour score {colour_score(render, rgb, gt):.3f}"
        )

        def adds_cm(T, g=g):
            return 100 * cKDTree(pts @ T[:3, :3].T + T[:3, 3]).query(g)[0].mean()

        refined = []
        for k, h in enumerate(hits):
            T = pose_from(lib, h, cam.K)
            line = (
                f"  significance {h.score:5.1f}  view {h.view_id:3d}  angle {np.degrees(h.angle_rad):5.1f}  "
                f"depth {h.depth_m:.2f} m  ADD-S {adds_cm(T):5.1f} cm  colour {colour_score(render, rgb, T):.3f}"
            )
            if k < args.refine:
                T2, s2, n = refine_colour(render, rgb, T, model.center_m)
                refined.append((s2, adds_cm(T2)))
                line += f"  -> refined: colour {s2:.3f}, ADD-S {adds_cm(T2):5.1f} cm ({n} renders)"
            print(line)
        if refined:
            s2, a2 = max(refined)
            print(
                f"  kept (highest colour score after refinement): ADD-S {a2:.1f} cm, colour {s2:.3f}; "
                f"{time.perf_counter() - t0:.1f} s with the search"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())

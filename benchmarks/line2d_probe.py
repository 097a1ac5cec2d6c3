"""LINE-2D probe (a prototype, not used by the pipeline): do gradient-orientation templates single out an
object SIFT misses in a cluttered frame?

For one object, the views of its template library (the nearer distance, every ``--view-step``-th) are
rendered once; each view's template is ``--features`` points on its silhouette's outline and its strong
inner edges, each with its gradient orientation (LINE-2D, Hinterstoisser et al. 2012: orientation bins
over a half turn). Turned in the image plane in 15-degree steps and scaled to object sizes from 48 px to
0.8 of the image height (factor 1.2), each is slid over the frame's orientation maps (edges spread
:data:`SPREAD` px, pooled to a :data:`GRID`-px grid): its score at a place is the share of its points that
meet an edge of their orientation there, less the mean share with the template moved 8 px eight ways (as
the verification score's outline term: dense clutter meets a template everywhere), over one less that mean.

Per frame showing the object it prints the best score anywhere and the best among the templates within 15 %
of the object's true size placed within a grid cell of its true centre: a search can find the object only
where the second comes near the first.

Usage:
    .venv/bin/python benchmarks/line2d_probe.py RUN_DIR --object NAME [--frames 4] [--view-step 4]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO  # noqa: E402  (puts the repo on sys.path)

from batchpose.config import load_estimator_config, load_yaml  # noqa: E402
from batchpose.core.frames import decode_image  # noqa: E402
from batchpose.io import library  # noqa: E402
from batchpose.io.manifest import load_manifest  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.io.sources import open_frames  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402
from batchpose.method.score import EDGE_STRENGTH, N_ORIENTATIONS, orientations  # noqa: E402

GRID = 4  # the search grid (px)
SPREAD = 1  # each frame edge counts this far (px) before pooling
NEIGHBOUR = 0.0  # credit for an edge one orientation bin off
SHIFT_CELLS = 2  # the template moved this many grid cells (8 px) for the clutter it meets anyway


@dataclass
class View:
    R: np.ndarray  # camera-from-model rotation of the view
    xy: np.ndarray  # (F, 2) feature offsets from the model centre's pixel, px in the render
    angle: np.ndarray  # (F,) gradient orientation, radians in [0, pi)
    span_px: float  # the object's diameter in the render


def response_maps(gray: np.ndarray) -> np.ndarray:
    """(8, H/GRID, W/GRID): for each template orientation bin, 1 where the frame has an edge of that bin near,
    0.5 where only of a neighbouring bin."""
    bins, strong = orientations(gray, EDGE_STRENGTH)
    k = np.ones((2 * SPREAD + 1, 2 * SPREAD + 1), np.uint8)
    h, w = gray.shape[0] // GRID, gray.shape[1] // GRID
    pooled = []
    for o in range(N_ORIENTATIONS):
        b = cv2.dilate((strong & (bins == o)).astype(np.uint8), k)
        pooled.append(cv2.resize(b, (w, h), interpolation=cv2.INTER_AREA) > 0)
    P = np.stack(pooled).astype(np.float32)
    return np.maximum(P, NEIGHBOUR * np.maximum(np.roll(P, 1, axis=0), np.roll(P, -1, axis=0)))


def make_views(lib, model, renderer, step: int, n_features: int) -> list[View]:
    dist = lib.views["distance_m"].to_numpy()
    f = 0.5 * (lib.K[0, 0] + lib.K[1, 1])
    out = []
    for v in np.flatnonzero(np.isclose(dist, dist.min()))[::step]:
        T = lib.cam_from_model(int(v))
        rgb, depth = renderer.render(model.content_hash, model.mesh, T, lib.K, lib.width, lib.height, "lit")
        mask = depth > 0
        if mask.sum() < 50:
            continue
        c = lib.K @ (T[:3, :3] @ model.center_m + T[:3, 3])
        c = c[:2] / c[2]
        m8 = mask.astype(np.uint8)
        outline = mask & (cv2.erode(m8, np.ones((3, 3), np.uint8)) == 0)
        mb = cv2.GaussianBlur(m8.astype(np.float32) * 255.0, (5, 5), 0)
        gx, gy = cv2.Sobel(mb, cv2.CV_32F, 1, 0), cv2.Sobel(mb, cv2.CV_32F, 0, 1)
        gray = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32), (3, 3), 0)
        hx, hy = cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1)
        inner = (cv2.erode(m8, np.ones((5, 5), np.uint8)) > 0) & (cv2.magnitude(hx, hy) >= 2 * EDGE_STRENGTH)
        ys, xs = np.nonzero(outline)
        a_out = np.arctan2(gy[ys, xs], gx[ys, xs])
        yi, xi = np.nonzero(inner)
        a_in = np.arctan2(hy[yi, xi], hx[yi, xi])
        pts = np.r_[np.c_[xs, ys], np.c_[xi, yi]].astype(np.float64)
        ang = np.r_[a_out, a_in] % np.pi
        chosen = _spread_out(pts, n_features, n_first=len(xs), first_share=0.6)
        span = f * model.diameter_m / float(dist[v])
        out.append(View(T[:3, :3].copy(), pts[chosen] - c, ang[chosen], span))
    return out


def _spread_out(pts: np.ndarray, n: int, n_first: int, first_share: float) -> np.ndarray:
    """Farthest-point sampling: ``first_share`` of the ``n`` from the first ``n_first`` points, the rest from all."""
    chosen: list[int] = []
    d = np.full(len(pts), np.inf)
    for pool_n, count in ((n_first, int(first_share * n)), (len(pts), n)):
        while len(chosen) < min(count, len(pts)):
            cand = d[:pool_n].copy()
            cand[chosen] = -1
            i = int(np.argmax(cand)) if chosen else 0
            if cand[i] <= 0 and chosen:
                break
            chosen.append(i)
            d = np.minimum(d, np.linalg.norm(pts - pts[i], axis=1))
    return np.asarray(chosen)


def scores(Rp: np.ndarray, pad: int, v: View, span: float, angle: float) -> np.ndarray:
    """The template of view ``v`` at ``span`` px and turned by ``angle``: its score at every grid cell."""
    h, w = Rp.shape[1] - 2 * pad, Rp.shape[2] - 2 * pad
    c, si = np.cos(angle), np.sin(angle)
    off = np.rint(span / v.span_px * v.xy @ np.array([[c, si], [-si, c]]) / GRID).astype(int)
    bins = ((((v.angle + angle) % np.pi) / np.pi) * N_ORIENTATIONS).astype(int) % N_ORIENTATIONS
    acc = np.zeros((h, w), np.float32)
    for (dx, dy), b in zip(off, bins, strict=True):
        acc += Rp[b, pad + dy : pad + dy + h, pad + dx : pad + dx + w]
    acc /= len(off)
    k = SHIFT_CELLS
    pa = np.pad(acc, k, mode="edge")
    shifts = ((k, 0), (-k, 0), (0, k), (0, -k), (k, k), (k, -k), (-k, k), (-k, -k))
    beside = np.mean([pa[k + dy : k + dy + h, k + dx : k + dx + w] for dy, dx in shifts], axis=0)
    return (acc - beside) / np.maximum(1.0 - beside, 0.05)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("run", type=Path, help="a finished run whose manifest shows the object (with ground truth)")
    ap.add_argument("--object", required=True)
    ap.add_argument("--frames", type=int, default=4, help="frames showing the object")
    ap.add_argument("--view-step", type=int, default=4)
    ap.add_argument("--features", type=int, default=40)
    ap.add_argument("--cache", type=Path, default=REPO / "runs" / "cache", help="the run's template cache")
    args = ap.parse_args()
    conf = load_estimator_config(load_yaml(args.run / "config.yaml")["pipeline"])
    man = load_manifest(args.run / "manifest.yaml")
    lib = library.load(next(p for p in (args.cache / "templates").glob(f"{args.object}-*") if library.is_cached(p)))
    obj = next(o for o in man.objects if o.name == args.object)
    model = load_mesh(obj.mesh, conf.mesh, name=args.object)
    views = make_views(lib, model, get_renderer(), args.view_step, args.features)
    angles = np.deg2rad(np.arange(0.0, 360.0, 15.0))
    print(f"# {args.object}: {len(views)} views x {len(angles)} turns")
    n = 0
    for f in open_frames(man.frames, man.path.parent):
        gt = next((g.cam_from_model for g in f.gt if g.obj_name == args.object), None)
        if gt is None:
            continue
        K, H = f.camera.K, f.camera.height
        centre = K @ (gt[:3, :3] @ model.center_m + gt[:3, 3])
        gx, gy = int(centre[0] / centre[2] // GRID), int(centre[1] / centre[2] // GRID)
        true_span = 0.5 * (K[0, 0] + K[1, 1]) * model.diameter_m / centre[2]
        spans = list(48.0 * 1.2 ** np.arange(int(np.log(0.8 * H / 48.0) / np.log(1.2)) + 1))
        R = response_maps(cv2.cvtColor(decode_image(f), cv2.COLOR_RGB2GRAY))
        pad = int(np.ceil(max(spans) / GRID)) + 1
        Rp = np.pad(R, ((0, 0), (pad, pad), (pad, pad)))
        anywhere = at_truth = -np.inf
        t0 = time.perf_counter()
        for v in views:
            for span in spans:
                for a in angles:
                    S = scores(Rp, pad, v, span, a)
                    anywhere = max(anywhere, float(S.max()))
                    if abs(np.log(span / true_span)) < 0.15:
                        at_truth = max(at_truth, float(S[max(gy - 1, 0) : gy + 2, max(gx - 1, 0) : gx + 2].max()))
        took = time.perf_counter() - t0
        print(f"{f.frame_id}: best anywhere {anywhere:.2f}, at the truth {at_truth:.2f} ({took:.1f} s)")
        n += 1
        if n == args.frames:
            break
    return 0


if __name__ == "__main__":
    sys.exit(main())

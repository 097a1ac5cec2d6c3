"""Accuracy on objects ycbv_dev does not have: every YCB mesh rendered into real YCB-Video frames.

ycbv_dev holds real frames of 7 objects; ``../shared/data/ycb_models`` holds 12. This script renders each
of them (lit, not the templates' flat shading) at random poses a YCB-Video camera would see (``--views``) —
distance 0.6–1.2 m, anywhere in the image, roll ±30° — into real ycbv_dev frames that do not show that
object, with a per-frame colour gain, defocus blur, sensor noise, JPEG compression and, in half of the
frames, a piece of another real frame (one that does not show the object either) covering 15–35 % of the
object. Each frame also gets a depth image (the background frame's sensor depth, moved back by one offset
where needed so that the object stands in front of its surroundings as the colour image shows it; the
object's rendered depth with 2 mm·z² noise and 3 % holes; the occluding piece 10 cm in front of the object),
used only by pipelines that read depth (``--pipeline rgbd``).

Two degradations make the frames score like real ones (``--scale-error``, ``--motion-blur``):

- **the colour image and the ground truth disagree in scale**: on real YCB-Video frames right RGB poses sit
  0.5–3.7 % too far (per video: the colour frames show the objects smaller than the mesh at the ground-truth
  pose, which follows the depth sensor; ``benchmarks/line_of_sight.py``). Each object is rendered with the
  focal lengths scaled down by a per-frame draw from that range (the ground truth and the intrinsics given
  to the run stay the true ones; the depth image follows the ground truth);
- **motion blur** of a hand-held camera: a line kernel of up to ``--motion-blur`` (4) px in a random direction.

The light (``--light``): ``headlight`` (the default) lights the object from the camera; ``above`` from a
direction drawn above the camera (a ceiling light: up to 31° either side of the image's up, tilted up to 39°
back over the camera or 27° forward over the scene; one a frame, or one a run), so that faces turned from it
are dim — a lighting no template library is rendered with (``render.shading`` "flat" draws the albedo, "lit"
a headlight).

The views (``--views``): ``table`` (the default) stands the object on one of its resting faces (trimesh's stable
poses, drawn by their probability), turned any way about the table's normal, and looks at it from 15–65°
above the table (``--elevation``), as YCB-Video's hand-held cameras look at objects on a table (ycbv_dev's
real videos: 31–42°, ``benchmarks/line_of_sight.py``); ``any`` draws the view direction uniformly over the
sphere, undersides included.

``--views any --scale-error 0 0 --motion-blur 0`` gives the frames of earlier versions (the occluders aside). With
``--real RUN`` (a finished ``batchpose run`` of ``data_manifest/ycbv_dev.yaml``) the objects with real
frames are compared with their scores on the real frames of that run.

Frames alone or in sequences (``--sequence L``): by default each frame stands alone (a background drawn
anew, im_ids two apart, so no frame is tracked from another). With ``--sequence L`` an object's frames come
in runs of ``L`` consecutive frames of one real video, the object standing at one place in the scene
throughout the run (moved with the camera, whose motion the video's ground truth gives), with one colour
gain, scale error, occluding piece and motion-blur direction a run, and the noise and the blur's length
drawn per frame; im_ids are consecutive within a run, so the pipeline tracks and carries the object through
it as it does through a recorded log (ycbv_dev's real frames are such sequences).

The frames are written as a BOP data set with ground truth and run through ``batchpose run``; the table
gives ADD-S / ADD AUC per object, marking the objects that are in ycbv_dev, and how many poses were reported
ok but are wrong (ADD-S > 0.1 diameter). A second table (``benchmarks/as_shown.py``) scores the same
estimates against the pose each image shows (the ground truth moved by the frame's scale disagreement,
written to ``data/<scene>/shown_scale.json``) and the most an estimator exactly right about the image can
score, with the precision of ok (ADD-S < 0.2 d) against each.

Usage:
    .venv/bin/python benchmarks/heldout.py [--frames 8] [--objects NAME ...] [--pipeline gnc_pose]
        [--keep DIR] [--cache DIR] [--seed 0] [--set KEY=VALUE ...] [--scale-error 0.5 3.7]
        [--motion-blur 4] [--views table|any] [--elevation 15 65] [--sequence 1] [--real RUN]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO, code_version, machine, table  # noqa: E402
from as_shown import report as as_shown_report  # noqa: E402

from batchpose.core.frames import decode_depth, decode_image  # noqa: E402
from batchpose.io.folders import YcbvFrameSource  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402
from batchpose.report.metrics import vocap_auc  # noqa: E402

DATA = REPO.parent / "shared" / "data"
MODELS = DATA / "ycb_models"
DEV = DATA / "ycbv_dev"
DEV_OBJECTS = (
    "002_master_chef_can",
    "003_cracker_box",
    "004_sugar_box",
    "006_mustard_bottle",
    "007_tuna_fish_can",
    "009_gelatin_box",
    "010_potted_meat_can",
)


#: How far behind an object drawn into a frame the middle of its surroundings' depth is put (:func:`behind`).
BEHIND_M = 0.05


def random_rotation(rng: np.random.Generator, max_roll_deg: float = 30.0) -> np.ndarray:
    """Camera-from-model rotation: a uniformly random view direction, then a roll about the optical axis."""
    from batchpose.method.views import look_at  # noqa: PLC0415

    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.95 else np.array([1.0, 0.0, 0.0])
    R = look_at(d, np.zeros(3), up)[:3, :3]
    return _roll(rng, max_roll_deg) @ R


def draw_light(light: str, stream: list[int]) -> np.ndarray | None:
    """``--light``: None for the headlight; for ``above``, a direction towards a light above the camera, in
    its axes (x right, y down), drawn from the random stream ``stream`` (its own, so other draws stay)."""
    if light != "above":
        return None
    rng = np.random.default_rng(stream)
    v = np.array([rng.uniform(-0.6, 0.6), -1.0, rng.uniform(-0.8, 0.5)])
    return v / np.linalg.norm(v)


def _roll(rng: np.random.Generator, max_roll_deg: float) -> np.ndarray:
    """A rotation about the optical axis by up to ``max_roll_deg`` either way."""
    a = np.deg2rad(rng.uniform(-max_roll_deg, max_roll_deg))
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def table_rotation(
    rng: np.random.Generator, stable: tuple[np.ndarray, np.ndarray], elevation_deg=(15.0, 65.0), max_roll_deg=30.0
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-from-model rotation of an object resting on a table, seen along the optical axis: one of its
    ``stable`` poses (trimesh's transforms and probabilities, drawn by probability), turned any way about the
    table's normal, the camera ``elevation_deg`` above the table, rolled about the optical axis; and the
    table's upward normal in the camera frame."""
    from batchpose.method.views import look_at  # noqa: PLC0415

    transforms, probs = stable
    on_table = transforms[rng.choice(len(probs), p=probs / probs.sum())][:3, :3]
    yaw = rng.uniform(0.0, 2.0 * np.pi)
    e = np.deg2rad(rng.uniform(*elevation_deg))
    R = look_at(np.array([np.cos(e), 0.0, np.sin(e)]), np.zeros(3), np.array([0.0, 0.0, 1.0]))[:3, :3]
    roll = _roll(rng, max_roll_deg)
    return roll @ R @ cv2.Rodrigues(np.array([0.0, 0.0, yaw]))[0] @ on_table, roll @ R @ np.array([0.0, 0.0, 1.0])


def place(
    R: np.ndarray, center_m: np.ndarray, K: np.ndarray, w: int, h: int, rng: np.random.Generator, on_ray=False
) -> np.ndarray:
    """cam_from_model with the object's centre 0.6–1.2 m away, projecting into the middle 60 % of the image.
    ``on_ray``: ``R`` is the rotation seen along the optical axis, turned with the ray to where the object is."""
    from batchpose.method.support import turn_to  # noqa: PLC0415

    z = rng.uniform(0.6, 1.2)
    u, v = rng.uniform(0.2 * w, 0.8 * w), rng.uniform(0.2 * h, 0.8 * h)
    c_cam = z * np.linalg.solve(K, np.array([u, v, 1.0]))
    if on_ray:
        R = turn_to(np.array([0.0, 0.0, 1.0]), c_cam / np.linalg.norm(c_cam)) @ R
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c_cam - R @ center_m
    return T


def compose(
    bg: np.ndarray,
    rgb: np.ndarray,
    depth: np.ndarray,
    occluder: np.ndarray | None,
    rng,
    bg_depth: np.ndarray,
    depth_rng,
    blur_px: float = 0.0,
    noise_rng: np.random.Generator | None = None,
    blur_angle: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The render over ``bg`` with a soft edge, colour gain, optional occluding patch, blur (a motion blur
    ``blur_px`` long in a direction from ``depth_rng``, then defocus) and noise; and the depth image a sensor
    would give of that (metres, 0: no reading; its noise from ``depth_rng``, so that the colour images are
    those of earlier versions of this script for the same seed). ``noise_rng``: the colour noise's draws
    (default ``rng``'s, after the others); ``blur_angle``: the motion blur's direction (radians; default a
    draw from ``depth_rng``)."""
    on = depth > 0
    z = np.where(on, depth, bg_depth).astype(np.float32)
    z = np.where(on, z + depth_rng.normal(0.0, 0.002, z.shape) * z**2, z)
    z[on & (depth_rng.random(z.shape) < 0.03)] = 0.0
    alpha = cv2.GaussianBlur((depth > 0).astype(np.float32), (3, 3), 0)[..., None]
    obj = rgb.astype(np.float32) * rng.uniform(0.75, 1.15) * rng.uniform(0.92, 1.08, size=3)
    out = alpha * obj + (1.0 - alpha) * bg.astype(np.float32)
    if occluder is not None:
        ys, xs = np.nonzero(depth > 0)
        x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
        frac = rng.uniform(0.15, 0.35)
        side = rng.integers(4)
        if side == 0:
            x1 = x0 + int(frac * (x1 - x0))
        elif side == 1:
            x0 = x1 - int(frac * (x1 - x0))
        elif side == 2:
            y1 = y0 + int(frac * (y1 - y0))
        else:
            y0 = y1 - int(frac * (y1 - y0))
        out[y0:y1, x0:x1] = occluder[y0:y1, x0:x1]
        z[y0:y1, x0:x1] = float(depth[on].min()) - 0.1
    if blur_px >= 1.0:
        angle = depth_rng.uniform(0.0, np.pi) if blur_angle is None else blur_angle
        out = cv2.filter2D(out, -1, motion_kernel(blur_px, angle))
    out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.5, 1.2))
    out += (rng if noise_rng is None else noise_rng).normal(0.0, 3.0, out.shape)
    return np.clip(out, 0, 255).astype(np.uint8), z


def behind(bg_depth: np.ndarray, depth: np.ndarray, margin_m: float = BEHIND_M) -> np.ndarray:
    """The background frame's depth image moved back by one offset, so that the object drawn over it (its
    rendered ``depth``) stands in front of what surrounds it, as the colour image shows it: the median reading
    of a band around its silhouette ``margin_m`` beyond the object's farthest point (about half of the band
    stands out behind it, as for an object on a table seen from above; unmoved where that holds already).
    Without it an object drawn at 1.1 m over a table 0.9 m away has a depth image no real scene gives."""
    on = depth > 0
    if not on.any():
        return bg_depth
    grow = int(np.ceil(0.03 * np.sqrt(on.sum()))) + 2
    band = (cv2.dilate(on.astype(np.uint8), np.ones((2 * grow + 1,) * 2, np.uint8)) > 0) & ~on & (bg_depth > 0)
    if not band.any():
        return bg_depth
    shift = float(depth[on].max()) + margin_m - float(np.median(bg_depth[band]))
    return np.where(bg_depth > 0, bg_depth + max(shift, 0.0), 0.0).astype(bg_depth.dtype)


def motion_kernel(length_px: float, angle: float) -> np.ndarray:
    """A normalised line kernel ``length_px`` long at ``angle`` (radians): a camera moving during exposure."""
    size = int(np.ceil(length_px)) | 1
    k = np.zeros((size, size), np.float32)
    c, d = size // 2, 0.5 * (length_px - 1.0)
    dx, dy = d * np.cos(angle), d * np.sin(angle)
    cv2.line(k, (round(c - dx), round(c - dy)), (round(c + dx), round(c + dy)), 1.0, 1, cv2.LINE_AA)
    return k / k.sum()


def generate(
    out: Path,
    objects: list[str],
    n: int,
    seed: int,
    scale_error=(0.5, 3.7),
    motion_blur: float = 4.0,
    views: str = "table",
    elevation=(15.0, 65.0),
    sequence: int = 1,
    light: str = "headlight",
) -> Path:
    """Write the BOP data set and its manifest; returns the manifest path. ``scale_error`` (percent, low and
    high), ``motion_blur`` (px), ``views``, ``elevation`` (degrees), ``sequence`` and ``light``: see the
    module docstring."""
    source = YcbvFrameSource(DEV)
    bgs = [(f, decode_image(f), decode_depth(f)) for f in source if f.scene_id < 10000]  # real frames only
    renderer = get_renderer()
    rng = np.random.default_rng(seed)
    names = {}
    for k, name in enumerate(objects, start=1):
        names[k] = name
        model = load_mesh(MODELS / name / "textured.obj", name=name)
        stable = model.mesh.compute_stable_poses(n_samples=1) if views == "table" else None
        usable = [(f, img, d) for f, img, d in bgs if name not in {g.obj_name for g in f.gt}]
        scene = out / "data" / f"{k:06d}"
        (scene / "rgb").mkdir(parents=True, exist_ok=True)
        (scene / "depth").mkdir(parents=True, exist_ok=True)
        cams, gts, shown = {}, {}, {}
        pose = None if stable is None else (lambda g, st=stable: table_rotation(g, st, elevation)[0])
        if sequence > 1:
            for r, start in enumerate(range(0, n, sequence)):
                run = _Run(k, r, min(sequence, n - start), seed, scale_error, motion_blur, light)
                run.write(scene, cams, gts, model, renderer, usable, pose, r * (sequence + 2))
                shown.update(dict.fromkeys(sorted(set(cams) - set(shown)), run.scale))
            _finish(scene, cams, gts, shown)
            continue
        for i in range(n):
            f, bg, bg_depth = usable[rng.integers(len(usable))]
            K, w, h = f.camera.K, f.camera.width, f.camera.height
            real = np.random.default_rng([seed, k, i, 1])  # its own stream: the poses stay those of the seed
            shown_K = K.copy()
            shown[str(2 * i)] = 1.0 - 0.01 * real.uniform(*scale_error)
            shown_K[:2, :2] *= shown[str(2 * i)]
            blur_px = real.uniform(0.0, motion_blur)
            T, rgb, depth = _inside(rng, pose, model, renderer, K, shown_K, w, h, draw_light(light, [seed, k, i, 2]))
            occluder = usable[rng.integers(len(usable))][1] if i % 2 else None  # not a piece showing the object
            backdrop = behind(bg_depth, depth)
            img, z = compose(bg, rgb, depth, occluder, rng, backdrop, np.random.default_rng([seed, k, i]), blur_px)
            _write(scene, 2 * i, img, z, K, T, k, cams, gts)
        _finish(scene, cams, gts, shown)
    manifest = out / "heldout.yaml"
    manifest.write_text(
        "# Generated by benchmarks/heldout.py: YCB meshes rendered into real ycbv_dev frames.\n"
        "name: heldout_synth\n"
        f"frames: {{format: bop, root: data, obj_names: {json.dumps(names)}}}\n"
        f"models: {{root: {MODELS}, mesh: '{{name}}/textured.obj', points: '{{name}}/points.xyz'}}\n"
        f"objects: {json.dumps(objects)}\n"
        "targets: annotations\n"
    )
    return manifest


class _Run:
    """``--sequence``: object ``k``'s ``r``-th run of ``length`` consecutive frames of one real video."""

    def __init__(
        self, k: int, r: int, length: int, seed: int, scale_error, motion_blur: float, light: str = "headlight"
    ) -> None:
        self.k, self.r, self.length, self.seed, self.motion_blur = k, r, length, seed, motion_blur
        self.rng = np.random.default_rng([seed, k, r, 11])  # the run's draws: video, place, scale, occluder
        self.scale = 1.0 - 0.01 * self.rng.uniform(*scale_error)
        self.blur_angle = self.rng.uniform(0.0, np.pi)  # a hand-held camera sways one way for a while
        self.light = draw_light(light, [seed, k, r, 14])

    def write(self, scene: Path, cams: dict, gts: dict, model, renderer, usable: list, pose, first_id: int) -> None:
        """Render the run into a stretch of a video that does not show the object (``usable``: background
        frames), ``pose``: callable(rng) -> camera-from-model rotation seen along the optical axis (None: any
        view); its frames get im_ids ``first_id``, ``first_id + 1``, ..."""
        rng, n = self.rng, self.length
        videos: dict[int, list] = {}
        for f, img, d in sorted(usable, key=lambda u: (u[0].scene_id, u[0].im_id)):
            videos.setdefault(f.scene_id, []).append((f, img, d))
        stretches = [v[i : i + n] for v in videos.values() for i in range(len(v) - n + 1)]
        stretches = [s for s in stretches if all(b[0].im_id == a[0].im_id + 1 for a, b in zip(s, s[1:], strict=False))]
        frames = stretches[rng.integers(len(stretches))]
        f0 = frames[0][0]
        K, w, h = f0.camera.K, f0.camera.width, f0.camera.height
        shown_K = K.copy()
        shown_K[:2, :2] *= self.scale
        T0 = _inside(rng, pose, model, renderer, K, shown_K, w, h, self.light)[0]  # in the first frame
        # The camera's motion from the video's ground truth: every object of a YCB-Video scene stands still.
        ref = f0.gt[0].obj_name
        world_from_cam0 = np.linalg.inv(f0.gt[0].cam_from_model)
        occluder = usable[rng.integers(len(usable))][1] if self.r % 2 else None
        for j, (f, bg, bg_depth) in enumerate(frames):
            T = next(g.cam_from_model for g in f.gt if g.obj_name == ref) @ world_from_cam0 @ T0
            rgb, depth = renderer.render(model.content_hash, model.mesh, T, shown_K, w, h, "lit", light_from=self.light)
            each = np.random.default_rng([self.seed, self.k, self.r, j, 13])
            blur_px = each.uniform(0.0, self.motion_blur)
            if not (depth > 0).any():
                continue  # the camera has turned away from it
            look = np.random.default_rng([self.seed, self.k, self.r, 12])  # the same gain and occluder each frame
            img, z = compose(
                bg, rgb, depth, occluder, look, behind(bg_depth, depth), each, blur_px, each, self.blur_angle
            )
            _write(scene, first_id + j, img, z, K, T, self.k, cams, gts)


def _inside(rng, pose, model, renderer, K, shown_K, w: int, h: int, light_from=None):
    """A pose drawn as :func:`place` draws it (``pose``: callable(rng) -> the rotation seen along the optical
    axis, None: any view) whose render stays inside the image (20 tries, else the last); (pose, rgb, depth)."""
    for _ in range(20):
        if pose is None:
            T = place(random_rotation(rng), model.center_m, K, w, h, rng)
        else:
            T = place(pose(rng), model.center_m, K, w, h, rng, on_ray=True)
        rgb, depth = renderer.render(model.content_hash, model.mesh, T, shown_K, w, h, "lit", light_from=light_from)
        ys, xs = np.nonzero(depth > 0)
        if len(xs) > 200 and xs.min() > 2 and ys.min() > 2 and xs.max() < w - 3 and ys.max() < h - 3:
            break
    return T, rgb, depth


def _finish(scene: Path, cams: dict, gts: dict, shown: dict) -> None:
    """A scene's BOP files, and ``shown_scale.json``: per im_id, the factor its object's focal lengths were
    scaled by (``--scale-error``; benchmarks/as_shown.py scores against the pose the image shows)."""
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    (scene / "scene_gt.json").write_text(json.dumps(gts))
    (scene / "shown_scale.json").write_text(json.dumps({i: shown[i] for i in cams}))


def _write(scene: Path, im_id: int, img: np.ndarray, z: np.ndarray, K, T, k: int, cams: dict, gts: dict) -> None:
    """One frame of the BOP data set: its colour and depth images, camera and ground truth."""
    cv2.imwrite(str(scene / "rgb" / f"{im_id:06d}.jpg"), img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
    tenths_mm = np.clip(np.rint(z * 10000.0), 0, 65535).astype(np.uint16)
    cv2.imwrite(str(scene / "depth" / f"{im_id:06d}.png"), tenths_mm)
    cams[str(im_id)] = {"cam_K": K.ravel().tolist(), "depth_scale": 0.1}
    gts[str(im_id)] = [{"obj_id": k, "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": (T[:3, 3] * 1000).tolist()}]


def run_options(ap: argparse.ArgumentParser) -> None:
    """The options of the ``batchpose run`` a generated data set goes through (see :func:`run_pipeline`)."""
    ap.add_argument("--pipeline", default="gnc_pose", help="name in pipelines/ or a YAML path")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", help="write the data set and the run here instead of a temporary folder")
    ap.add_argument("--cache", help="template cache folder (default: the run's own)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="pipeline override")


def run_pipeline(manifest: Path, out: Path, args, limit: int | None = None) -> None:
    """``batchpose run`` on ``manifest`` into ``out`` with the :func:`run_options` in ``args``."""
    pipeline = args.pipeline if args.pipeline.endswith(".yaml") else str(REPO / "pipelines" / f"{args.pipeline}.yaml")
    cmd = [sys.executable, "-m", "batchpose", "run", pipeline, "--manifest", str(manifest), "--out", str(out)]
    cmd += ["--jobs", str(args.jobs), "--overwrite"]
    if limit:
        cmd += ["--limit", str(limit)]
    if args.cache:
        cmd += ["--cache", args.cache]
    for s in args.set:
        cmd += ["--set", s]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=REPO)


def against_real(per: pd.DataFrame, run: Path) -> list[list[str]]:
    """Rows comparing the synthetic scores (``per``, summary rows) of the objects with real ycbv_dev frames
    with their scores on the real frames (not ``data_syn``) of the ycbv_dev run ``run``."""
    inst = pd.read_csv(run / "report" / "frames.csv")
    inst = inst[~inst["frame_id"].astype(str).str.startswith("data_syn")]
    rows, syn, real = [], [], []
    for r in per[per["obj_name"].isin(set(inst["obj_name"]))].itertuples():
        g = inst[inst["obj_name"] == r.obj_name]
        a, b = vocap_auc(g["adds_m"].to_numpy(float)), vocap_auc(g["add_m"].to_numpy(float))
        syn.append((r.adds_auc, r.add_auc))
        real.append((a, b))
        rows.append([f"{r.obj_name}, real frames", "dev", f"{int((g['status'] == 'ok').sum())}/{len(g)}", "",
                     f"{a:.1f}", f"{b:.1f}", "", "", ""])  # fmt: skip
    if syn:
        (sa, sb), (ra, rb) = np.mean(syn, axis=0), np.mean(real, axis=0)
        rows.append(["mean of those, synthetic", "", "", "", f"{sa:.1f}", f"{sb:.1f}", "", "", ""])
        rows.append(["mean of those, real frames", "", "", "", f"{ra:.1f}", f"{rb:.1f}", "", "", ""])
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=8, help="frames per object (default 8)")
    ap.add_argument("--objects", nargs="+", help="object names (default: every mesh in ../shared/data/ycb_models)")
    ap.add_argument(
        "--scale-error",
        nargs=2,
        type=float,
        default=(0.5, 3.7),
        metavar=("LO", "HI"),
        help="objects shown this many percent smaller than the ground truth (default 0.5 3.7)",
    )
    ap.add_argument("--motion-blur", type=float, default=4.0, help="longest motion blur, px (default 4)")
    ap.add_argument(
        "--views", choices=("table", "any"), default="table", help="resting on a table (default) or any direction"
    )
    ap.add_argument(
        "--elevation",
        nargs=2,
        type=float,
        default=(15.0, 65.0),
        metavar=("LO", "HI"),
        help="--views table: the camera this many degrees above the table (default 15 65)",
    )
    ap.add_argument(
        "--light", choices=("headlight", "above"), default="headlight", help="light from the camera or from above"
    )
    ap.add_argument(
        "--sequence", type=int, default=1, metavar="L", help="frames in runs of L consecutive ones (default 1: alone)"
    )
    ap.add_argument("--real", type=Path, help="a ycbv_dev run: compare with its real frames' scores")
    run_options(ap)
    args = ap.parse_args()
    if not MODELS.is_dir() or not DEV.is_dir():
        print(f"N/A: {DATA} not found (needs ycb_models and ycbv_dev)")
        return 0
    objects = args.objects or sorted(
        p.name for p in MODELS.iterdir() if (p / "textured.obj").is_file() and (p / "points.xyz").is_file()
    )
    out = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="batchpose_heldout_"))
    print(
        f"# heldout: {machine()}; code {code_version()}; {len(objects)} objects x {args.frames} frames, "
        f"views {args.views}, sequences of {args.sequence} -> {out}"
    )
    manifest = generate(
        out,
        objects,
        args.frames,
        args.seed,
        tuple(args.scale_error),
        args.motion_blur,
        args.views,
        tuple(args.elevation),
        args.sequence,
        args.light,
    )
    run_pipeline(manifest, out / "run", args)
    summary = pd.read_csv(out / "run" / "report" / "summary.csv")
    per = summary[~summary["obj_name"].isin(["mean", "pooled"])].copy()
    # A wrong pose reported ok misleads a user more than a failure: count them (ADD-S > 0.1 diameter).
    inst = pd.read_csv(out / "run" / "report" / "frames.csv")
    ok = inst[inst["status"] == "ok"]
    wrong = (ok["adds_m"] > 0.1 * ok["diameter_m"]).groupby(ok["obj_name"]).sum()
    rows = []
    for r in per.itertuples():
        rows.append(
            [
                r.obj_name,
                "dev" if r.obj_name in DEV_OBJECTS else "held out",
                f"{r.n_ok}/{r.n}",
                int(wrong.get(r.obj_name, 0)),
                f"{r.adds_auc:.1f}",
                f"{r.add_auc:.1f}",
                f"{r.add_recall_01d:.0f} %",
                f"{r.median_rot_err_deg:.1f}",
                f"{r.median_trans_err_mm:.1f}",
            ]
        )
    held = per[~per["obj_name"].isin(DEV_OBJECTS)]
    for label, part in (("mean, held-out objects", held), ("mean, all objects", per)):
        if len(part):
            rows.append([label, "", "", "", f"{part.adds_auc.mean():.1f}", f"{part.add_auc.mean():.1f}", "", "", ""])
    rows.append(["total", "", f"{len(ok)}/{len(inst)}", int(wrong.sum()), "", "", "", "", ""])
    if args.real:
        rows += against_real(per, args.real)
    print(
        table(
            rows,
            [
                "object",
                "in ycbv_dev",
                "ok",
                "ok but wrong",
                "ADD-S AUC",
                "ADD AUC",
                "ADD < 0.1 d",
                "median rot °",
                "median trans mm",
            ],
        )
    )
    print("\nAgainst the pose the image shows (benchmarks/as_shown.py; --scale-error):")
    print(as_shown_report([out]))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""MCAP throughput: write a 640x480 JPEG log, read it (with and without decoding), write poses back.

Every frame is a distinct JPEG (a shifted crop of a large random texture with a moving rectangle,
encoded once per frame at quality 90), so the reader cannot benefit from repeated bytes.

Usage:
    .venv/bin/python benchmarks/mcap_throughput.py [--frames 1000] [--keep DIR]
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh
from PIL import Image

from batchpose.core.frames import Camera, Frame, decode_image
from batchpose.io.gltf import mesh_to_glb
from batchpose.io.mcap_poses import write_poses_mcap
from batchpose.io.mcap_read import McapFrameSource
from batchpose.io.mcap_write import write_frames_mcap

W, H = 640, 480
K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])


def make_frames(n: int, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    texture = cv2.resize(
        rng.integers(0, 256, (120, 160, 3), dtype=np.uint8), (2 * W, 2 * H), interpolation=cv2.INTER_CUBIC
    )
    texture = cv2.add(texture, rng.integers(0, 16, texture.shape, dtype=np.uint8))  # fine grain
    cam = Camera(K=K, width=W, height=H)
    frames = []
    for i in range(n):
        x, y = (i * 7) % W, (i * 5) % H
        img = texture[y : y + H, x : x + W].copy()
        cv2.rectangle(img, (50 + i % 400, 60), (150 + i % 400, 200), (255, 255, 255), -1)
        data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
        frames.append(Frame(f"{i:06d}", 0, i, i * 33_333_333, cam, "jpeg", data))
    return frames


def make_records(stamps: list[int], rng: np.random.Generator) -> list[dict]:
    rows = []
    for s in stamps:
        R = cv2.Rodrigues(rng.normal(size=3) * 0.3)[0]
        t = [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.5, 0.8)]
        rows.append(
            {
                "frame_id": f"mcap:{s}",
                "stamp_ns": s,
                "obj_name": "box",
                "status": "ok",
                "reason": "",
                "R": R.reshape(-1).tolist(),
                "t_m": t,
                "confidence": 0.9,
                "n_inliers": 60,
                "inliers_px": rng.uniform(0, 480, 120).tolist(),
            }
        )
    return rows


def textured_box_glb() -> bytes:
    mesh = trimesh.creation.box(extents=(0.1, 0.15, 0.2))
    uv = np.random.default_rng(1).random((len(mesh.vertices), 2))
    tex = Image.fromarray(np.random.default_rng(2).integers(0, 256, (4096, 4096, 3), dtype=np.uint8))
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, image=tex)
    return mesh_to_glb(mesh)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--keep", help="write the logs here instead of a temporary folder")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    t = time.perf_counter()
    frames = make_frames(args.frames)
    mb = sum(len(f.image_data) for f in frames) / 1e6
    print(f"generated {len(frames)} distinct {W}x{H} JPEGs ({mb:.1f} MB) in {time.perf_counter() - t:.1f} s")

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(args.keep) if args.keep else Path(tmp)
        d.mkdir(parents=True, exist_ok=True)
        log_path, out_path = d / "frames.mcap", d / "poses.mcap"

        t = time.perf_counter()
        write_frames_mcap(frames, log_path)
        dt_write = time.perf_counter() - t

        src = McapFrameSource(log_path)
        t = time.perf_counter()
        n = sum(1 for _ in src)
        dt_ingest = time.perf_counter() - t

        t = time.perf_counter()
        for f in src:
            decode_image(f)
        dt_decode = time.perf_counter() - t

        glb = textured_box_glb()
        rows = make_records([f.stamp_ns for f in frames], np.random.default_rng(3))
        t = time.perf_counter()
        write_poses_mcap(out_path, rows, {"box": glb}, input_mcap=log_path)
        dt_back = time.perf_counter() - t

        print(
            f"log {log_path.stat().st_size / 1e6:.1f} MB, poses log {out_path.stat().st_size / 1e6:.1f} MB "
            f"(glb {len(glb) / 1e3:.0f} kB)"
        )
        print(f"write frames (convert)  : {n / dt_write:8.0f} frames/s  ({dt_write:.2f} s)")
        print(f"ingest only             : {n / dt_ingest:8.0f} frames/s  ({dt_ingest:.2f} s)")
        print(f"ingest + JPEG decode    : {n / dt_decode:8.0f} frames/s  ({dt_decode:.2f} s)")
        print(f"write-back (copy+poses) : {n / dt_back:8.0f} frames/s  ({dt_back:.2f} s)")


if __name__ == "__main__":
    main()

"""Report stage on a small synthetic run directory: CSV values, HTML content, and a real headless browser."""

from __future__ import annotations

import base64
import fcntl
import json
import math
import os
import re
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import trimesh
import yaml

from batchpose.core.poses import PoseRecord
from batchpose.errors import DataError, MeshError
from batchpose.report import figures, overlays, runs, scoring
from batchpose.report import html as report_html
from batchpose.stages import report as report_stage
from tests.conftest import rotation

W, H = 160, 120
K = np.array([[200.0, 0.0, 80.0], [0.0, 200.0, 60.0], [0.0, 0.0, 1.0]])
FRAME_IDS = ["f000", "f001", "f002", "f003"]
BOX_A = np.array([0.10, 0.06, 0.04])  # obj_a: a box, points file; diameter = |BOX_A| = 0.1233 m
BOX_B = np.array([0.05, 0.05, 0.08])  # obj_b: a mesh, no points file (sampled)

try:
    import batchpose.io.folders  # noqa: F401

    HAVE_DATASETS = True
except ImportError:
    HAVE_DATASETS = False


def _T(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _gt_pose(obj: str, k: int) -> np.ndarray:
    R = rotation(0, 20 + 10 * k) @ rotation(1, 15 * k)
    return _T(R, [-0.05, 0.0, 0.6]) if obj == "obj_a" else _T(R, [0.06, 0.01, 0.6])


def make_run(
    root: Path,
    with_gt: bool = True,
    frames_root: Path | None = None,
    shift_mm: float = 10.0,
    turn_b_deg: float = 0.0,
    model_scale: float = 1.0,
    wrong_b_mm: float = 0.0,
) -> Path:
    """Write a run directory in the pipeline's layout (4 frames, 2 objects).

    ``turn_b_deg`` turns obj_b's estimates about its x axis; ``wrong_b_mm`` moves obj_b's (ok) estimate in
    f001 that far from the camera (300: ADD-S > 0.19 m, since two copies of a convex object 0.106 m across
    moved 0.3 m apart are at least 0.194 m apart, so the pose is wrong however the box is turned);
    ``model_scale`` multiplies the coordinates of
    obj_a's points file and obj_b's mesh (1000: millimetre files), while objects.json keeps the metre
    diameters, as ``batchpose run`` writes them after converting a millimetre mesh.
    """
    run = root / "run"
    data = root / "data"
    img_dir = data / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for k, fid in enumerate(FRAME_IDS):
        noise = cv2.GaussianBlur(rng.integers(0, 255, (H, W, 3), dtype=np.uint8), (0, 0), 3)
        img = cv2.addWeighted(noise, 0.6, np.full_like(noise, 60 + 30 * k), 0.4, 0)
        cv2.imwrite(str(img_dir / f"{fid}.png"), img)
    (img_dir / "intrinsics.yaml").write_text(
        yaml.safe_dump({"fx": 200.0, "fy": 200.0, "cx": 80.0, "cy": 60.0, "width": W, "height": H})
    )

    pts_a = trimesh.sample.sample_surface(trimesh.creation.box(extents=BOX_A), 300, seed=1)[0]
    np.savetxt(data / "obj_a.xyz", pts_a * model_scale, fmt="%.6f")
    trimesh.creation.box(extents=BOX_B * model_scale).export(data / "obj_b.ply")
    objects = {
        "obj_a": {
            "obj_id": 1,
            "mesh": str(data / "obj_a.ply"),
            "points": str(data / "obj_a.xyz"),
            "diameter_m": float(np.linalg.norm(BOX_A)),
        },
        "obj_b": {
            "obj_id": 2,
            "mesh": str(data / "obj_b.ply"),
            "points": None,
            "diameter_m": float(np.linalg.norm(BOX_B)),
        },
    }
    run.mkdir(parents=True)
    (run / "objects.json").write_text(json.dumps(objects, indent=1))

    frames = pd.DataFrame(
        [
            {
                "frame_id": fid,
                "scene_id": 0,
                "im_id": k,
                "stamp_ns": k * 33_333_333,
                "width": W,
                "height": H,
                "K": K.ravel().tolist(),
                "source": str(img_dir / f"{fid}.png"),
            }
            for k, fid in enumerate(FRAME_IDS)
        ]
    )
    frames.to_parquet(run / "frames.parquet")
    if not with_gt:  # what ingest writes for a data set without ground truth: an empty table
        pd.DataFrame(columns=["frame_id", "obj_name", "obj_id", "R", "t_m"]).to_parquet(run / "gt.parquet")
    else:
        gt = pd.DataFrame(
            [
                {
                    "frame_id": fid,
                    "obj_name": obj,
                    "obj_id": objects[obj]["obj_id"],
                    "R": _gt_pose(obj, k)[:3, :3].ravel().tolist(),
                    "t_m": _gt_pose(obj, k)[:3, 3].tolist(),
                }
                for k, fid in enumerate(FRAME_IDS)
                for obj in ("obj_a", "obj_b")
            ]
        )
        gt.to_parquet(run / "gt.parquet")

    recs = []
    shift = np.eye(4)
    shift[0, 3] = shift_mm / 1000.0
    for k, fid in enumerate(FRAME_IDS):
        common = {
            "scene_id": 0,
            "im_id": k,
            "stamp_ns": k * 33_333_333,
            "timings": {"decode": 0.002, "sift": 0.1 + 0.01 * k, "match": 0.02, "gnc": 0.005},
        }
        # obj_a: exact, exact, 10 mm off along x, failed.
        if k < 3:
            T = shift @ _gt_pose("obj_a", k) if k == 2 else _gt_pose("obj_a", k)
            recs.append(
                PoseRecord(
                    fid,
                    "obj_a",
                    "ok",
                    obj_id=1,
                    cam_from_model=T,
                    confidence=0.9 - 0.2 * k,
                    n_matches=80,
                    n_inliers=40 - 10 * k,
                    **common,
                )
            )
        else:
            recs.append(
                PoseRecord(fid, "obj_a", "too_few_matches", reason="4 matches < 6", obj_id=1, n_matches=4, **common)
            )
        # obj_b: exact three times (f001 moved away by wrong_b_mm), no row at all for the last frame.
        if k < 3:
            away = _T(np.eye(3), [0.0, 0.0, wrong_b_mm / 1000.0 if k == 1 else 0.0])
            recs.append(
                PoseRecord(
                    fid,
                    "obj_b",
                    "ok",
                    obj_id=2,
                    cam_from_model=away @ _gt_pose("obj_b", k) @ _T(rotation(0, turn_b_deg), [0.0, 0.0, 0.0]),
                    confidence=0.8,
                    n_matches=60,
                    n_inliers=30,
                    **common,
                )
            )
    pd.DataFrame([r.to_row() for r in recs]).to_parquet(run / "poses.parquet")

    (run / "config.yaml").write_text("name: test\ngnc:\n  kappa: 5.0\n  gamma: 0.5\n")
    (run / "versions.json").write_text(
        json.dumps({"batchpose": "0.1.0", "numpy": np.__version__, "opencv": cv2.__version__})
    )
    spec = {
        "format": "images",
        "root": str(frames_root or img_dir),
        "intrinsics": str(img_dir / "intrinsics.yaml"),
    }
    manifest = {"name": "synthetic boxes", "frames": spec, "objects": sorted(objects)}
    (run / "manifest.yaml").write_text(yaml.safe_dump(manifest))
    return run


def _imgs(html: str) -> dict[str, str]:
    """id -> base64 payload of every <img> (asserting each has an alt): plots inline PNG, overlays JPEG."""
    out = {}
    for tag in re.findall(r"<img\b[^>]*>", html):
        id_ = re.search(r'\bid="([^"]+)"', tag)
        assert id_ and re.search(r'\balt="[^"]+"', tag), tag[:120]
        kind = "jpeg" if id_.group(1).startswith("overlay-") else "png"
        src = re.search(rf'\bsrc="data:image/{kind};base64,([^"]*)"', tag)
        assert src, f"{id_.group(1)}: not an inline {kind}"
        out[id_.group(1)] = src.group(1)
    return out


def _decodes(b64: str) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.size > 0
    return img


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    """The report of a run with ground truth: one of its 6 ok poses wrong (obj_b in f001, 300 mm away)."""
    run = make_run(tmp_path_factory.mktemp("report"), wrong_b_mm=300.0)
    return report_stage.main(None, None, run)


@pytest.fixture(scope="module")
def report_nogt(tmp_path_factory) -> Path:
    """The report of the same run without ground truth (an empty gt.parquet, as ingest writes it)."""
    return report_stage.main(None, None, make_run(tmp_path_factory.mktemp("nogt"), with_gt=False))


def test_summary_csv(report):
    s = pd.read_csv(report / "summary.csv").set_index("obj_name")
    assert list(s.index) == ["obj_a", "obj_b", "mean", "pooled"]
    # obj_a ADD: d = [0, 0, .01, inf] (n = 4): rec = [0, 0, 0, .01, .1], prec = [0, .25, .5, .75, .75]
    #   -> (.01*.75 + .09*.75)/.1*100 = 75. Its ADD-S (<= 10 mm) gives 75 too: the area only depends on
    #   the accuracy .75 reached at any distance below 0.1. obj_b: d = [0, >.19, 0, inf] -> 50 (ADD .3 m and
    #   ADD-S > .19 m are beyond the curve's 0.1 m). Pooled: 5 of 8 below 0.1 m -> 62.5.
    for obj, auc in (("obj_a", 75.0), ("obj_b", 50.0), ("mean", 62.5), ("pooled", 62.5)):
        assert s.loc[obj, "add_auc"] == pytest.approx(auc)
        assert s.loc[obj, "adds_auc"] == pytest.approx(auc)
    # 0.1 d of obj_a is 12.3 mm, so the 10 mm shift passes: 3 / 4.
    assert s.loc["obj_a", "add_recall_01d"] == pytest.approx(75.0)
    assert s.loc["obj_a", "median_trans_err_mm"] == pytest.approx(0.0, abs=1e-9)  # median of 0, 0, 10
    assert s.loc["obj_a", "n_too_few_matches"] == 1 and s.loc["obj_b", "n_missing"] == 1
    assert s.loc["pooled", "n"] == 8 and s.loc["pooled", "n_ok"] == 6
    assert s.loc["obj_a", "paper_adds_auc"] != s.loc["obj_a", "paper_adds_auc"]  # NaN: not a paper object
    # The verdict's counts of estimated (frame, object) pairs: obj_b's f003 has no row, so it is no pair.
    pairs = s[["n_pairs", "n_pairs_ok", "n_ok_wrong", "n_pairs_failed"]]
    assert pairs.loc["obj_a"].tolist() == [4, 3, 0, 1]
    assert pairs.loc["obj_b"].tolist() == [3, 3, 1, 0]
    assert pairs.loc["pooled"].tolist() == pairs.loc["mean"].tolist() == [7, 6, 1, 1]
    assert list(s.columns[:5]) == ["n_pairs", "n_pairs_ok", "n_ok_wrong", "n_pairs_failed", "n"]
    # BOP ARs (no depth images here, so no VSD). obj_a: exact, exact, 10 mm sideways, failed. The shift is an
    # MSSD of 10 mm: below 9 of the 10 thresholds 0.05 d .. 0.5 d (d = 123 mm); its 3.0-3.7 px in the image
    # (200 px focal, 0.54-0.66 m deep) are below 8 of 1.25 .. 12.5 px (5 .. 50 px x 160 / 640).
    # obj_b: exact, 0.3 m away, exact, missing.
    assert "ar_vsd" not in s.columns
    assert s.loc["obj_a", "ar_mssd"] == pytest.approx((1 + 1 + 0.9 + 0) / 4)
    assert s.loc["obj_a", "ar_mspd"] == pytest.approx((1 + 1 + 0.8 + 0) / 4)
    assert s.loc["obj_a", "ar"] == pytest.approx((1 + 1 + 0.85 + 0) / 4)
    # obj_b's 0.3 m along the line of sight moves its image by only 12.2 px: below the top MSPD threshold
    # (12.5 px), so it scores 0.1 there (MSPD cannot see depth), 0 under MSSD.
    assert s.loc["obj_b", "ar_mssd"] == pytest.approx(0.5) and s.loc["obj_b", "ar_mspd"] == pytest.approx(0.525)
    assert s.loc["mean", "ar"] == s.loc["pooled", "ar"] == pytest.approx((0.7125 + 0.5125) / 2)
    # ok precision / recall (correct: ADD-S < 0.2 d): obj_a 3 of 3 ok correct, 3 of 4 instances; obj_b 2 of
    # 3, 2 of 4; pooled 5 of 6, 5 of 8; mean of the objects' values.
    expected = {"obj_a": (1.0, 0.75), "obj_b": (2 / 3, 0.5), "pooled": (5 / 6, 5 / 8), "mean": (5 / 6, 0.625)}
    for obj, (p, r) in expected.items():
        assert (s.loc[obj, "ok_precision"], s.loc[obj, "ok_recall"]) == (pytest.approx(p), pytest.approx(r)), obj
    assert s["n_ok_absent"].sum() == 0 and s["n_absent_pairs"].sum() == 0  # only ground-truth objects asked


def test_frames_csv(report):
    f = pd.read_csv(report / "frames.csv")
    assert len(f) == 8
    a = f[f["obj_name"] == "obj_a"].set_index("frame_id")
    assert list(a["status"]) == ["ok", "ok", "ok", "too_few_matches"]
    assert a.loc["f002", "add_m"] == pytest.approx(0.01)
    assert a.loc["f002", "trans_err_mm"] == pytest.approx(10.0)
    assert a.loc["f002", "rot_err_deg"] == pytest.approx(0.0, abs=1e-5)
    assert math.isinf(a.loc["f003", "add_m"]) and a.loc["f003", "reason"] == "4 matches < 6"
    assert list(a["im_id"]) == [0, 1, 2, 3]
    b = f[f["obj_name"] == "obj_b"].set_index("frame_id")
    assert b.loc["f003", "status"] == "missing"
    assert b.loc["f001", "status"] == "ok" and b.loc["f001", "add_m"] == pytest.approx(0.3)
    assert b.loc["f001", "adds_m"] > 0.19
    # The BOP errors per instance: the 10 mm shift, a missed pose as +inf with recall 0.
    assert a.loc["f002", "mssd_mm"] == pytest.approx(10.0) and 3.0 < a.loc["f002", "mspd_px"] < 3.75
    assert math.isinf(a.loc["f003", "mssd_mm"]) and a.loc["f003", "ar"] == 0.0
    assert b.loc["f001", "mssd_mm"] == pytest.approx(300.0) and b.loc["f001", "ar"] == pytest.approx(0.05)
    assert a.loc["f000", "ar_mssd"] == a.loc["f000", "ar_mspd"] == a.loc["f000", "ar"] == 1.0


def _near(img: np.ndarray, bgr: tuple[int, int, int], tol: int = 40) -> int:
    """Pixels of a (JPEG) BGR image within ``tol`` of a colour in every channel."""
    return int(np.all(np.abs(img.astype(int) - bgr) <= tol, axis=2).sum())


def test_html_content(report):
    html = (report / "index.html").read_text()
    assert 'id="results-table"' in html
    assert "reported by the paper on a different test set" in html
    assert not re.search(r"<script|<link|\b(src|href)=\"https?:", html)  # self-contained
    assert "<title>synthetic boxes</title>" in html and "<h1>synthetic boxes</h1>" in html  # the manifest's name
    # Provenance is collapsed; the verdict comes before every section.
    for part in ("objects", "versions", "manifest", "config"):
        assert re.search(rf'<details id="details-{part}"><summary>', html), part
    assert html.index('id="verdict"') < html.index("<section")
    imgs = _imgs(html)
    assert re.search(
        r'ok precision <b id="verdict-ok-precision">0.833</b> · ok recall <b id="verdict-ok-recall">0.625</b>', html
    )
    assert '<th class="bop">AR MSSD</th>' in html and "AR VSD" not in html
    assert "VSD left out: 4 of 4 frames have no depth image" in html  # why, in the run section's notes
    for id_ in ("plot-curves", "plot-errors", "plot-confidence", "plot-values"):
        assert _decodes(imgs[id_]).shape[1] >= 500
    assert _decodes(imgs["plot-pr"]).shape[1] >= 400  # one small figure
    if not HAVE_DATASETS:
        assert 'id="gallery-note"' in html
        return
    # 6 ok instances: the worse half (3) is "worst", the others "best"; failures (too few matches, no
    # estimate) show ground truth only. Worst first, each object's worst before a second case of an object.
    overlays = [k for k in imgs if k.startswith("overlay-") and not k.endswith("-full")]
    assert overlays == [
        f"overlay-{g}-{i}" for g, n in (("worst", 3), ("failed", 2), ("best", 3)) for i in range(1, n + 1)
    ]
    titles = re.findall(r"<figcaption><b>([^<]+)</b><br>([^<]+)</figcaption>", html)
    assert titles[0][0] == "f001 · obj_b" and "wrong" in titles[0][1]  # the wrong pose leads
    assert titles[1][0] == "f002 · obj_a"  # obj_a's worst (10 mm), before a second obj_b case
    assert {t for t, _ in titles[3:5]} == {"f003 · obj_a", "f003 · obj_b"}
    assert "too few matches: 4 matches &lt; 6 (ground truth only)" in html
    for k in overlays:  # a JPEG thumbnail, and its full-size JPEG in a lightbox the thumbnail links to
        assert _decodes(imgs[k]).shape[0] == 240 and _decodes(imgs[f"{k}-full"]).shape[0] >= 480
        assert f'<a class="thumb" href="#full-{k}">' in html and f'<div class="lightbox" id="full-{k}">' in html
    worst = _decodes(imgs["overlay-worst-2"])  # obj_a, 10 mm off: both poses in the crop
    assert abs(worst.shape[1] - 320) <= 2  # 4:3 crop
    # Both colours are drawn: ground truth green and the estimate orange (BGR here; JPEG: nearly).
    assert _near(worst, (60, 200, 40)) > 50 and _near(worst, (0, 140, 255)) > 50
    assert "gallery-note" not in html


def test_ok_pose_of_an_absent_object_is_a_false_positive(tmp_path):
    """Without obj_b's ground truth in f000, its ok pose there is a pose of an absent object: wrong for the
    precision, counted in the verdict's absent line."""
    run = make_run(tmp_path)
    gt = pd.read_parquet(run / "gt.parquet")
    gt[~((gt["frame_id"] == "f000") & (gt["obj_name"] == "obj_b"))].to_parquet(run / "gt.parquet")
    out = report_stage.main(None, None, run)
    s = pd.read_csv(out / "summary.csv").set_index("obj_name")
    assert s.loc["obj_b", ["n_ok_absent", "n_absent_pairs"]].tolist() == [1, 1]
    assert s.loc["obj_a", ["n_ok_absent", "n_absent_pairs"]].tolist() == [0, 0]
    # obj_b: ok in f000 (absent), f001 and f002 (right); its instances f001, f002, f003.
    assert s.loc["obj_b", "ok_precision"] == pytest.approx(2 / 3) and s.loc["obj_b", "ok_recall"] == pytest.approx(
        2 / 3
    )
    html = (out / "index.html").read_text()
    assert re.search(r'<span id="verdict-absent" class="wrong"><b>1</b> ok poses of objects absent', html)
    assert "of 1 (frame, absent object) pairs estimated (100.0 %)" in html and "verdict-unchecked" not in html


def test_a_run_without_any_ok_pose_is_reported(tmp_path):
    """Every pair absent (e.g. a log of frames without the objects): the report is written, recall 0, no
    precision, nothing carried."""
    run = make_run(tmp_path)
    poses = pd.read_parquet(run / "poses.parquet")
    poses["status"] = "absent"
    poses.to_parquet(run / "poses.parquet")
    out = report_stage.main(None, None, run)
    s = pd.read_csv(out / "summary.csv").set_index("obj_name")
    assert s.loc["pooled", "ok_recall"] == 0 and np.isnan(s.loc["pooled", "ok_precision"])
    assert s.loc["pooled", "n_carried"] == 0


def test_overlay_draws_at_projected_pose():
    rgb = np.zeros((H, W, 3), np.uint8)
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    img = overlays.draw_overlay(rgb, K, pts, [(_T(np.eye(3), [0, 0, 1.0]), (255, 0, 0))], out_height=H)
    assert img.shape[0] == H and img[..., 0].max() == 255 and img[..., 1].max() == 0


#: What a reader of a report without ground truth must not see (summary.csv's raw names, raw statuses).
RAW_NAMES = ("n_too_few_matches", "too_few_matches", "detection_rate_pct", "median_confidence", "obj_name", "n_ok")


def test_report_without_ground_truth(report_nogt):
    out = report_nogt
    s = pd.read_csv(out / "summary.csv").set_index("obj_name")
    # obj_a: 3 ok of 4 rows; obj_b: 3 of 3 (its missing frame has no row); all: 6 / 7.
    assert s.loc["obj_a", "detection_rate_pct"] == pytest.approx(75.0)
    assert s.loc["obj_b", "detection_rate_pct"] == pytest.approx(100.0)
    assert s.loc["all", "detection_rate_pct"] == pytest.approx(600 / 7)
    assert s.loc["obj_a", "median_confidence"] == pytest.approx(0.7)
    assert s.loc["all", ["n_pairs", "n_pairs_ok", "n_pairs_failed"]].tolist() == [7, 6, 1]
    assert "n_ok_wrong" not in s.columns  # no ground truth: no pose is called wrong
    assert len(pd.read_csv(out / "frames.csv")) == 7
    html = (out / "index.html").read_text()
    imgs = _imgs(html)
    assert "plot-confidence" in imgs and 'id="results-table"' in html
    # Readable labels: headers and statuses in words, none of summary.csv's column names.
    header = re.search(r'<table id="results-table"><thead><tr>(.*?)</tr>', html).group(1)
    assert re.findall(r"<th>([^<]*)</th>", header) == [
        "Object",
        "pairs",
        "ok",
        "detection rate (%)",
        "median confidence (ok)",
        "too few matches",
    ]
    assert "<td>all objects</td>" in html
    assert 'id="verdict-failed-kinds">(not found 1: too few matches 1)' in html
    for raw in RAW_NAMES:
        assert raw not in html, raw
    if HAVE_DATASETS:
        assert sum(k.startswith("overlay-least-confident") and not k.endswith("-full") for k in imgs) == 3
        assert sum(k.startswith("overlay-most-confident") and not k.endswith("-full") for k in imgs) == 3


def test_gallery_failure_is_explained(tmp_path):
    run = make_run(tmp_path, frames_root=tmp_path / "nowhere")
    html = (report_stage.main(None, None, run) / "index.html").read_text()
    note = re.search(r'<p class="warn" id="gallery-note">([^<]*)</p>', html)
    assert note, "the report must say why there is no gallery"
    assert ("does not exist" in note.group(1)) if HAVE_DATASETS else ("unavailable" in note.group(1))
    assert not any(k.startswith("overlay-") for k in _imgs(html))
    assert 'id="results-table"' in html


def test_rerun_skips_and_overwrite_rebuilds(tmp_path, caplog):
    run = make_run(tmp_path)
    index = report_stage.main(None, None, run) / "index.html"
    before = index.stat().st_mtime_ns
    with caplog.at_level("INFO", logger="batchpose"):
        report_stage.main(None, None, run)
    assert index.stat().st_mtime_ns == before and "Skipping report" in caplog.text
    report_stage.main(None, None, run, overwrite=True)
    assert index.stat().st_mtime_ns > before
    assert not list((run / "report").glob("*.tmp"))


def test_missing_poses_is_a_data_error(tmp_path):
    with pytest.raises(DataError, match="no poses.parquet"):
        report_stage.main(None, None, tmp_path)
    (tmp_path / "config.yaml").write_text("pipeline: {}\n")  # a run killed before its poses were merged
    with pytest.raises(DataError, match="the run is unfinished .* rerun the same `batchpose run` command"):
        report_stage.main(None, None, tmp_path)


def test_compare(tmp_path):
    good = make_run(tmp_path / "good")
    bad = make_run(tmp_path / "bad", shift_mm=50.0)  # obj_a's third estimate 50 mm off
    nogt = make_run(tmp_path / "nogt", with_gt=False)
    out = report_stage.compare([good, bad, nogt], tmp_path / "cmp")
    table = pd.read_csv(out / "compare.csv")
    assert list(table["run"]) == ["good/run", "bad/run", "nogt/run"]
    assert table.loc[0, "add_auc_pooled"] == pytest.approx(75.0)
    # 50 mm > 0.1 d (12.3 mm): recall drops from 6/8 to 5/8; the AUC stays 75 (right-end rule, d < 0.1 m).
    assert table.loc[0, "add_recall_01d"] == pytest.approx(75.0)
    assert table.loc[1, "add_recall_01d"] == pytest.approx(62.5)
    assert math.isnan(table.loc[2, "add_auc_pooled"]) and table.loc[2, "n_ok"] == 6
    # ADD-S lets a box slide along its own faces, so the 50 mm pose stays correct (ADD-S < 0.2 d) for the
    # precision and recall of ok; its MSSD (50 mm = 0.41 d) passes 2 of 10 thresholds instead of 9 (10 mm).
    assert table.loc[:1, "ok_precision"].tolist() == [1.0, 1.0]
    assert table.loc[:1, "ok_recall"].tolist() == [pytest.approx(6 / 8)] * 2
    assert table.loc[0, "ar_pooled"] > table.loc[1, "ar_pooled"]
    html = (out / "index.html").read_text()
    imgs = _imgs(html)
    assert set(imgs) == {"plot-compare-adds", "plot-compare-add"} and 'id="compare-table"' in html


# --- model units --------------------------------------------------------------------------------------


def _summary(run: Path) -> pd.DataFrame:
    return pd.read_csv(report_stage.main(None, None, run) / "summary.csv").set_index("obj_name")


def test_millimetre_models_score_like_metres(tmp_path, caplog):
    # obj_b's estimates are turned by 2 degrees, so its ADD depends on the model points' scale (about 1 mm
    # in metres; about 1 m, i.e. a failure, with unconverted millimetre points).
    metre = _summary(make_run(tmp_path / "m", turn_b_deg=2.0))
    with caplog.at_level("WARNING", logger="batchpose"):
        milli = _summary(make_run(tmp_path / "mm", turn_b_deg=2.0, model_scale=1000.0))
    pd.testing.assert_frame_equal(milli, metre, rtol=1e-6)
    assert "obj_a.xyz: the points span" in caplog.text and "scaling by 0.001" in caplog.text  # points file
    assert "obj_b.ply: bounding-box diagonal" in caplog.text  # mesh, by the estimator's rule
    # d = [a, a, a, inf] with a ~ 1 mm -> AUC = (0.1 - a) * 0.75 / 0.1 * 100, just below 75.
    assert 73.0 < metre.loc["obj_b", "add_auc"] < 75.0 and metre.loc["obj_b", "add_recall_01d"] == 75.0
    assert metre.loc["obj_a", "add_auc"] == pytest.approx(75.0)


def test_score_command_converts_millimetre_models(tmp_path):
    from batchpose.io import bop_csv as bop

    printed = []
    for sub, scale in (("m", 1.0), ("mm", 1000.0)):
        run = make_run(tmp_path / sub, turn_b_deg=2.0, model_scale=scale)
        csv = bop.write_bop_csv(pd.read_parquet(run / "poses.parquet"), tmp_path / sub / "res.csv")
        # A subprocess: the CLI configures the "batchpose" logger for the whole process.
        done = subprocess.run(
            [sys.executable, "-m", "batchpose", "score", str(csv), str(run)], capture_output=True, text=True
        )
        assert done.returncode == 0, done.stderr
        printed.append(done.stdout)
    assert printed[1] == printed[0]
    row_b = next(r for r in (line.split() for line in printed[0].splitlines()) if r[:1] == ["obj_b"])
    assert 73.0 < float(row_b[2]) < 75.0  # ADD-S AUC, not 0


@pytest.mark.parametrize("scale", [100.0, 0.5])
def test_points_file_in_other_units_is_refused(tmp_path, scale):
    # Centimetres, or points of an object half the mesh's size: neither metres nor millimetres of the mesh.
    run = make_run(tmp_path)
    pts = np.loadtxt(tmp_path / "data" / "obj_a.xyz")
    np.savetxt(tmp_path / "data" / "obj_a.xyz", pts * scale, fmt="%.6f")
    with pytest.raises(DataError, match=r"obj_a\.points: .*obj_a\.xyz: the points span .* neither in metres nor"):
        report_stage.main(None, None, run)


def test_millimetre_models_refused_with_on_millimetres_refuse(tmp_path):
    run = make_run(tmp_path, model_scale=1000.0)
    (run / "config.yaml").write_text(yaml.safe_dump({"pipeline": {"mesh": {"on_millimetres": "refuse"}}}))
    with pytest.raises(DataError, match=r"obj_a\.xyz: .*look like millimetres; .*on_millimetres: convert"):
        report_stage.main(None, None, run)
    objects = json.loads((run / "objects.json").read_text())
    objects["obj_a"]["points"] = None  # mesh samples instead: the mesh's own refusal, as in load_mesh
    objects["obj_a"]["mesh"] = objects["obj_b"]["mesh"]
    objects["obj_a"]["diameter_m"] = objects["obj_b"]["diameter_m"]
    (run / "objects.json").write_text(json.dumps(objects))
    with pytest.raises(MeshError, match=r"obj_b\.ply: .*looks like millimetres; .*on_millimetres: convert"):
        report_stage.main(None, None, run)


def _scaled_obj(src: Path, dst_dir: Path, scale: float) -> Path:
    """Copy an OBJ with its material and texture, vertex coordinates multiplied by ``scale``."""
    dst_dir.mkdir(parents=True)
    for f in src.parent.iterdir():
        if f.suffix != ".obj":
            shutil.copy(f, dst_dir / f.name)
    lines = []
    for line in src.read_text().splitlines():
        if line.startswith("v "):
            line = "v " + " ".join(f"{float(x) * scale:.6f}" for x in line.split()[1:4])
        lines.append(line)
    dst = dst_dir / src.name
    dst.write_text("\n".join(lines) + "\n")
    return dst


def test_unit_scale_is_load_mesh_rule(tmp_path):
    from batchpose.config import MeshConfig
    from batchpose.io.mesh import load_mesh, unit_scale
    from tests.conftest import GELATIN

    mm = _scaled_obj(GELATIN, tmp_path / "mm", 1000.0)
    for path, conf in [
        (GELATIN, MeshConfig()),
        (mm, MeshConfig()),
        (mm, MeshConfig(units="m")),
        (GELATIN, MeshConfig(units="mm")),
        (GELATIN, MeshConfig(on_millimetres="refuse")),
    ]:
        bounds = trimesh.load(path, force="mesh", process=False, skip_materials=True).bounds
        assert unit_scale(path, bounds, conf) == load_mesh(path, conf).scale
    with pytest.raises(MeshError, match="looks like millimetres") as helper:
        unit_scale(
            mm,
            trimesh.load(mm, force="mesh", process=False, skip_materials=True).bounds,
            MeshConfig(on_millimetres="refuse"),
        )
    with pytest.raises(MeshError) as loader:
        load_mesh(mm, MeshConfig(on_millimetres="refuse"))
    assert str(helper.value) == str(loader.value)
    # The report's model points of the millimetre mesh are the metre mesh's, and span its diameter_m.
    objects = {
        n: {"mesh": str(p), "points": None, "diameter_m": load_mesh(GELATIN).diameter_m}
        for n, p in [("m", GELATIN), ("mm", mm)]
    }
    points, _ = runs.load_model_points(objects, ["m", "mm"])
    np.testing.assert_allclose(points["mm"], points["m"], atol=1e-8)


# --- real browser ------------------------------------------------------------------------------------


def _find_browser() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


@pytest.fixture(scope="session")
def chromium() -> str:
    browser = _find_browser()
    if browser:
        return browser
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        pytest.skip("no chromium and not root, so it cannot be installed (apt-get install chromium)")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = ["apt-get", "install", "-y", "-q", "chromium"]
    if subprocess.run(install, check=False, env=env, capture_output=True, timeout=900).returncode != 0:
        subprocess.run(["apt-get", "update", "-q"], check=False, env=env, capture_output=True, timeout=600)
        done = subprocess.run(install, check=False, env=env, capture_output=True, text=True, timeout=900)
        if done.returncode != 0:
            pytest.skip(f"cannot install chromium: {done.stderr.strip()[-300:]}")
    browser = _find_browser()
    if not browser:
        pytest.skip("chromium installed but not on PATH")
    return browser


class Browser:
    """Headless Chromium driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``: fd 3 in,
    fd 4 out, NUL-separated JSON): real page loads, clicks and screenshots, without network or extra packages."""

    def __init__(self, executable: str, profile: Path, width: int = 1280, height: int = 800):
        to_child, self._out = os.pipe()
        self._in, from_child = os.pipe()
        # The child's ends above fd 9, so that moving them to 3 and 4 cannot overwrite one with the other.
        r, w = (fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10) for fd in (to_child, from_child))
        os.close(to_child)
        os.close(from_child)
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--remote-debugging-pipe", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--hide-scrollbars", f"--user-data-dir={profile}"]  # fmt: skip
        # A trampoline (not preexec_fn, unsafe with threads) puts them on fds 3 and 4, then becomes the browser.
        move = f"import os, sys; os.dup2({r}, 3); os.dup2({w}, 4); os.execv(sys.argv[1], sys.argv[1:])"
        self.proc = subprocess.Popen(
            [sys.executable, "-c", move, executable, *flags, "about:blank"],
            pass_fds=(r, w),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        os.close(r)
        os.close(w)
        self._buf, self._id, self.events = b"", 0, []
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            self.call(f"{domain}.enable", page=True)
        self.call("Emulation.setDeviceMetricsOverride", page=True, width=width, height=height,
                  deviceScaleFactor=1, mobile=False)  # fmt: skip

    def _message(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._in], [], [], left)[0]:
                raise TimeoutError("no answer from the browser")
            chunk = os.read(self._in, 1 << 20)
            if not chunk:
                raise EOFError("the browser closed its pipe")
            self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def call(self, method: str, page: bool = False, timeout: float = 60, **params) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params, **({"sessionId": self.session} if page else {})}
        os.write(self._out, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            answer = self._message(deadline)
            if answer.get("id") == self._id:
                assert "error" not in answer, f"{method}: {answer['error']}"
                return answer["result"]
            self.events.append(answer)

    def wait_for(self, event: str, timeout: float = 60) -> dict:
        deadline = time.monotonic() + timeout
        while not any(e.get("method") == event for e in self.events):
            self.events.append(self._message(deadline))
        return self.events.pop(next(i for i, e in enumerate(self.events) if e.get("method") == event))

    def open(self, url: str) -> None:
        self.call("Page.navigate", page=True, url=url)
        self.wait_for("Page.loadEventFired")

    def js(self, expression: str):
        result = self.call("Runtime.evaluate", page=True, expression=expression, returnByValue=True)
        assert "exceptionDetails" not in result, result
        return result["result"].get("value")

    def click(self, x: float, y: float) -> None:
        for kind in ("mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", page=True, type=kind, x=x, y=y, button="left", clickCount=1)

    def screenshot(self, path: Path) -> np.ndarray:
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", page=True, format="png")["data"]))
        return cv2.imread(str(path))

    def errors(self) -> list[str]:
        """Console errors, uncaught exceptions and browser log errors (blocked loads) so far."""
        out = [e["params"]["entry"]["text"] for e in self.events if e.get("method") == "Log.entryAdded"
               and e["params"]["entry"]["level"] == "error"]  # fmt: skip
        out += [str(e["params"]) for e in self.events if e.get("method") == "Runtime.exceptionThrown"]
        return out + [str(e["params"]["args"]) for e in self.events
                      if e.get("method") == "Runtime.consoleAPICalled" and e["params"]["type"] == "error"]  # fmt: skip

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=10)
        except (TimeoutError, EOFError, AssertionError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._in)
        os.close(self._out)


@pytest.fixture(scope="module")
def browser(chromium, tmp_path_factory):
    b = Browser(chromium, tmp_path_factory.mktemp("chromium") / "profile")
    yield b
    b.close()


def _first_screen(browser: Browser, name: str, tmp_path: Path) -> np.ndarray:
    """The page's first screen (1280 x 800), kept in $BATCHPOSE_SCREENSHOT_DIR when that is set."""
    shot = browser.screenshot(tmp_path / name)
    if os.environ.get("BATCHPOSE_SCREENSHOT_DIR"):
        shutil.copy(tmp_path / name, Path(os.environ["BATCHPOSE_SCREENSHOT_DIR"]) / name)
    assert shot.shape[:2] == (800, 1280) and shot.std() > 20, "screenshot looks blank"
    return shot


@pytest.mark.slow
def test_report_in_browser(report, browser, tmp_path):
    browser.open((report / "index.html").resolve().as_uri())
    assert browser.js("document.title") == "synthetic boxes"
    # The verdict, first on the page, counts what poses.parquet holds; obj_b in f001 is the one wrong pose.
    poses = pd.read_parquet(report.parent / "poses.parquet")
    frames = pd.read_csv(report / "frames.csv")
    pooled = pd.read_csv(report / "summary.csv").set_index("obj_name").loc["pooled"]
    ok = frames[frames["status"] == "ok"]
    n_wrong = int((ok["adds_m"] > 0.1 * ok["diameter_m"]).sum())
    shown = browser.js(
        "Object.fromEntries(['pairs', 'ok', 'wrong', 'failed', 'adds-auc', 'add-auc'].map("
        "k => [k, document.getElementById('verdict-' + k).textContent]))"
    )
    assert shown == {
        "pairs": str(len(poses)),
        "ok": str(int((poses["status"] == "ok").sum())),
        "wrong": str(n_wrong),
        "failed": str(int((poses["status"] != "ok").sum())),
        "adds-auc": f"{pooled['adds_auc']:.1f}",
        "add-auc": f"{pooled['add_auc']:.1f}",
    }
    assert n_wrong == 1 and shown["pairs"] == "7" and shown["failed"] == "1"
    assert browser.js("document.getElementById('verdict').getBoundingClientRect().bottom") < 400  # first screen
    assert "(not found 1: too few matches 1)" in browser.js("document.getElementById('verdict').textContent")
    assert browser.js("[...document.querySelectorAll('details')].every(d => !d.open)")  # provenance collapsed
    assert browser.js("[...document.images].every(i => i.complete && i.naturalWidth > 0)")  # all decode
    shot = _first_screen(browser, "report-gt.png", tmp_path)
    assert (shot.mean(axis=2) < 200).mean() > 0.01  # text and tables, not just white
    if not HAVE_DATASETS:
        return
    # Clicking an overlay opens its full-size image over the page; clicking that closes it.
    thumb = "document.getElementById('overlay-worst-1')"
    x, y = browser.js(f"(() => {{ {thumb}.scrollIntoView({{block: 'center'}}); const r = {thumb}"
                      ".getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2]; })()")  # fmt: skip
    assert browser.js("getComputedStyle(document.getElementById('full-overlay-worst-1')).display") == "none"
    browser.click(x, y)
    assert browser.js("location.hash") == "#full-overlay-worst-1"
    full = "document.getElementById('overlay-worst-1-full')"
    assert browser.js(f"document.elementFromPoint(640, 400) === {full}")  # the full image covers the screen
    size = browser.js(f"[{full}.naturalHeight, {thumb}.naturalHeight, {full}.getBoundingClientRect().height]")
    assert size[0] >= 480 and size[1] == 240 and size[2] >= 1.9 * size[1]  # shown twice the thumbnail's size
    browser.click(640, 400)
    assert browser.js("getComputedStyle(document.getElementById('full-overlay-worst-1')).display") == "none"
    assert not browser.errors()


@pytest.mark.slow
def test_report_without_ground_truth_in_browser(report_nogt, browser, tmp_path):
    browser.open((report_nogt / "index.html").resolve().as_uri())
    text = browser.js("document.body.innerText")  # what a reader sees (collapsed sections excluded)
    columns = [c for c in pd.read_csv(report_nogt / "summary.csv").columns if "_" in c]  # not "n"
    for raw in (*RAW_NAMES, *columns):
        assert raw not in text, raw
    for label in ("too few matches", "detection rate (%)", "all objects", "No ground truth"):
        assert label in text, label
    assert browser.js("document.getElementById('verdict-wrong')") is None
    assert browser.js("document.getElementById('verdict-pairs').textContent") == "7"
    _first_screen(browser, "report-nogt.png", tmp_path)
    assert not browser.errors()


def test_timeline_shows_each_pairs_status_and_the_most_severe_per_column():
    rows = pd.DataFrame(
        {
            "status": ["ok", "ok", "ok", "low_confidence", "hidden", "pnp_failed", "ok", "conflict"],
            "tracked": [False, True, None, False, False, False, False, True],
        }
    )
    wrong = np.array([False, False, False, False, False, False, True, False])
    kinds = figures.timeline_kinds(rows, wrong)
    names = [figures.TIMELINE_KINDS[k][0] for k in kinds]
    assert names == [
        "ok, full estimate",
        "ok, tracked",
        "ok, full estimate",
        "low confidence, region conflict",
        "hidden",
        "failed",
        "ok but wrong (ADD-S > 0.1 d)",
        "low confidence, region conflict",
    ]
    # Two objects over 0..3 s in 2 columns: a column shows its most severe pair, white (-1) where none.
    t = np.array([0.0, 1.0, 2.0, 3.0, 0.0])
    obj = np.array(["a", "a", "a", "a", "b"])
    kind = np.array([5, 1, 4, 5, 3])
    grid = figures.timeline_grid(t, obj, kind, ["a", "b"], columns=2)
    np.testing.assert_array_equal(grid, [[1, 4], [3, -1]])


def test_timeline_section_in_both_reports(report, report_nogt):
    assert {"plot-timeline", "plot-values"} <= set(_imgs((report / "index.html").read_text()))
    html = (report_nogt / "index.html").read_text()
    assert 'id="timeline"' in html and "confidence of its ok poses" in html
    # Separate image files: the axis is the frames' order, not seconds.
    assert "so the axis is their order in the run." in html
    assert _decodes(_imgs(html)["plot-timeline"]).shape[1] >= 900


def test_time_axis_is_log_time_only_for_one_log():
    poses = pd.DataFrame({"frame_id": ["a", "b", "c", "c", "d"]})
    one_log = pd.DataFrame(
        {
            "frame_id": ["a", "b", "c", "d"],
            "stamp_ns": [5_000_000_000, 5_500_000_000, 7_000_000_000, 7_100_000_000],
            "scene_id": [0, 0, 0, 0],
            "source": ["log.mcap:/camera/image"] * 4,
        }
    )
    axis = figures.time_axis(poses, one_log)
    assert axis.log_time and axis.breaks == [] and axis.n_frames == 4
    np.testing.assert_allclose(axis.x, [0.0, 0.5, 2.0, 2.0, 2.1])
    # Image files of two scenes, with invented stamps: frame order, the second scene's start marked.
    folders = one_log.assign(scene_id=[0, 0, 3, 3], source=[f"/data/{f}.png" for f in "abcd"])
    axis = figures.time_axis(poses, folders)
    assert not axis.log_time and axis.breaks == [(0.0, "scene 0"), (2.0, "scene 3")]
    np.testing.assert_allclose(axis.x, [0, 1, 2, 2, 3])
    # One source but stamps going back (a second pass over the log): frame order too.
    assert not figures.time_axis(poses, one_log.assign(stamp_ns=[3, 4, 1, 2])).log_time
    # Without frames.parquet: the poses' frames in order of first appearance.
    np.testing.assert_allclose(figures.time_axis(poses, None).x, [0, 1, 2, 2, 3])
    assert figures.time_axis(poses.iloc[:1], None) is None


def test_spread_shows_each_object_then_new_frames():
    rows = pd.DataFrame(
        {"frame_id": ["f1", "f2", "f3", "f1", "f4", "f2"], "obj_name": ["a", "a", "a", "b", "a", "c"]},
        index=[10, 11, 12, 13, 14, 15],
    )
    assert overlays.spread(rows, 3).index.tolist() == [10, 13, 15]  # each object's first
    assert overlays.spread(rows, 5).index.tolist() == [10, 13, 15, 12, 14]  # then frames not shown
    assert overlays.spread(rows, 9).index.tolist() == [10, 13, 15, 12, 14, 11]  # then the rest
    assert overlays.spread(rows.iloc[:0], 3).empty


def test_verdict_counts_pairs_and_groups_failures():
    poses = pd.DataFrame(
        {
            "frame_id": ["f0", "f0", "f1", "f1", "f2", "f2", "f2", "f3", "f4"],
            "obj_name": ["a", "b", "a", "b", "a", "b", "b", "a", "a"],
            "status": ["ok", "ok", "ok", "hidden", "too_few_matches", "pnp_failed", "ok", "weird_new", "ok"],
            "confidence": [0.9, 0.8, 0.7, 0.0, 0.0, 0.0, 0.6, 0.0, 0.5],
        }
    )
    # b in f2 has a failed and an ok row: one pair, ok (the scored row). a in f1 is wrong (ADD-S > 0.1 d);
    # a in f4 has no ground truth, so it cannot be wrong.
    per_instance = pd.DataFrame(
        {
            "frame_id": ["f0", "f0", "f1", "f2", "f9"],
            "obj_name": ["a", "b", "a", "b", "a"],
            "status": ["ok", "ok", "ok", "ok", "missing"],
            "adds_m": [0.001, 0.002, 0.05, 0.01, np.inf],
            "diameter_m": [0.2, 0.1, 0.2, 0.1, 0.2],
        }
    )
    pairs = scoring.pair_table(poses, per_instance)
    assert len(pairs) == 8 and pairs["wrong"].tolist().count(True) == 1 and pairs["checked"].sum() == 4
    summary = pd.DataFrame({"obj_name": ["a", "b", "pooled"], "n": [3, 2, 5], "n_missing": [1, 0, 1]})
    summary = summary.assign(adds_auc=[0, 0, 61.5], add_auc=[0, 0, 42.0])
    v = scoring.verdict(pairs, 4, summary)
    assert (v.n_pairs, v.n_ok, v.n_wrong, v.n_failed, v.n_no_estimate, v.n_ok_unchecked) == (8, 5, 1, 3, 1, 1)
    assert v.failed == [
        ("not found", 1, "too few matches 1"),
        ("hidden", 1, "hidden 1"),
        ("other", 1, "weird new 1"),
    ]
    assert report_html.verdict_text(v) == (
        "8 (frame, object) pairs: 5 ok (1 wrong: ADD-S > 0.1 d), 3 failed (not found 1: too few matches 1; "
        "hidden 1; other 1: weird new 1); ADD-S AUC 61.5, ADD AUC 42.0 (pooled, 5 instances)"
    )
    # With the precision, recall and AR columns, and ok poses of absent objects, the verdict says them too.
    trust = {"ok_precision": 0.8, "ok_recall": 0.5, "ar": 0.4567, "n_ok_absent": 2, "n_absent_pairs": 8}
    v = scoring.verdict(pairs, 4, summary.assign(**trust))
    assert (v.ok_precision, v.ok_recall, v.ar, v.n_ok_absent, v.n_absent_pairs) == (0.8, 0.5, 0.4567, 2, 8)
    assert report_html.verdict_text(v).endswith(
        "; ok precision 0.800, recall 0.500 (ADD-S < 0.2 d); BOP AR 0.457; 2 ok of 8 pairs of absent objects"
    )
    counts = scoring.with_pair_counts(summary, pairs, has_gt=True).set_index("obj_name")
    assert counts.loc["a", list(scoring.PAIR_COLUMNS)].tolist() == [5, 3, 1, 2]
    assert counts.loc["pooled", list(scoring.PAIR_COLUMNS)].tolist() == [8, 5, 1, 3]
    assert scoring.verdict(scoring.pair_table(poses, None), 4).n_wrong is None

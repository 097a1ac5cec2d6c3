"""Report stage on a small synthetic run directory: CSV values, HTML content, and a real headless browser."""

from __future__ import annotations

import base64
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import trimesh
import yaml

from batchpose.core.poses import PoseRecord
from batchpose.errors import DataError, MeshError
from batchpose.report import figures, overlays, runs
from batchpose.stages import report as report_stage

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


def _rot(axis: int, deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _T(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _gt_pose(obj: str, k: int) -> np.ndarray:
    R = _rot(0, 20 + 10 * k) @ _rot(1, 15 * k)
    return _T(R, [-0.05, 0.0, 0.6]) if obj == "obj_a" else _T(R, [0.06, 0.01, 0.6])


def make_run(
    root: Path,
    with_gt: bool = True,
    frames_root: Path | None = None,
    shift_mm: float = 10.0,
    turn_b_deg: float = 0.0,
    model_scale: float = 1.0,
) -> Path:
    """Write a run directory in the pipeline's layout (4 frames, 2 objects).

    ``turn_b_deg`` turns obj_b's estimates about its x axis; ``model_scale`` multiplies the coordinates of
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
    if with_gt:
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
        # obj_b: exact three times, no row at all for the last frame.
        if k < 3:
            recs.append(
                PoseRecord(
                    fid,
                    "obj_b",
                    "ok",
                    obj_id=2,
                    cam_from_model=_gt_pose("obj_b", k) @ _T(_rot(0, turn_b_deg), [0.0, 0.0, 0.0]),
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
    (run / "manifest.yaml").write_text(yaml.safe_dump({"frames": spec, "objects": sorted(objects)}))
    return run


def _imgs(html: str) -> dict[str, str]:
    """id -> base64 payload of every <img> (asserting each has an alt)."""
    out = {}
    for tag in re.findall(r"<img\b[^>]*>", html):
        id_ = re.search(r'\bid="([^"]+)"', tag)
        assert id_ and re.search(r'\balt="[^"]+"', tag), tag[:120]
        src = re.search(r'\bsrc="data:image/png;base64,([^"]*)"', tag)
        assert src, f"{id_.group(1)}: not an inline PNG"
        out[id_.group(1)] = src.group(1)
    return out


def _decodes(b64: str) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.size > 0
    return img


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    run = make_run(tmp_path_factory.mktemp("report"))
    return report_stage.main(None, None, run)


def test_summary_csv(report):
    s = pd.read_csv(report / "summary.csv").set_index("obj_name")
    assert list(s.index) == ["obj_a", "obj_b", "mean", "pooled"]
    # obj_a ADD: d = [0, 0, .01, inf] (n = 4): rec = [0, 0, 0, .01, .1], prec = [0, .25, .5, .75, .75]
    #   -> (.01*.75 + .09*.75)/.1*100 = 75. Its ADD-S (<= 10 mm) gives 75 too: the area only depends on
    #   the accuracy .75 reached at any distance below 0.1. obj_b: d = [0, 0, 0, inf] -> 75.
    for obj in ("obj_a", "obj_b", "mean", "pooled"):
        assert s.loc[obj, "add_auc"] == pytest.approx(75.0)
        assert s.loc[obj, "adds_auc"] == pytest.approx(75.0)
    # 0.1 d of obj_a is 12.3 mm, so the 10 mm shift passes: 3 / 4.
    assert s.loc["obj_a", "add_recall_01d"] == pytest.approx(75.0)
    assert s.loc["obj_a", "median_trans_err_mm"] == pytest.approx(0.0, abs=1e-9)  # median of 0, 0, 10
    assert s.loc["obj_a", "n_too_few_matches"] == 1 and s.loc["obj_b", "n_missing"] == 1
    assert s.loc["pooled", "n"] == 8 and s.loc["pooled", "n_ok"] == 6
    assert s.loc["obj_a", "paper_adds_auc"] != s.loc["obj_a", "paper_adds_auc"]  # NaN: not a paper object


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


def test_html_content(report):
    html = (report / "index.html").read_text()
    assert 'id="results-table"' in html
    assert "reported by the paper on a different test set" in html
    assert not re.search(r"<script|<link|\b(src|href)=\"https?:", html)  # self-contained
    imgs = _imgs(html)
    for id_ in ("plot-curve-adds", "plot-curve-add", "plot-errors", "plot-confidence"):
        assert _decodes(imgs[id_]).shape[1] >= 500
    if HAVE_DATASETS:
        # 6 ok instances: best 4, worst 2; failures (too_few_matches, missing) show ground truth only.
        overlays = sorted(k for k in imgs if k.startswith("overlay-"))
        assert overlays == [
            "overlay-best-1",
            "overlay-best-2",
            "overlay-best-3",
            "overlay-best-4",
            "overlay-failed-1",
            "overlay-failed-2",
            "overlay-worst-1",
            "overlay-worst-2",
        ]
        worst = _decodes(imgs["overlay-worst-1"])
        assert worst.shape[0] == 200 and abs(worst.shape[1] - 267) <= 2  # 4:3 crop
        # Both colours are drawn: ground truth green and the 10 mm-off estimate orange (BGR here).
        assert np.any(np.all(worst == (60, 200, 40), axis=2)) and np.any(np.all(worst == (0, 140, 255), axis=2))
        assert "gallery-note" not in html
    else:
        assert 'id="gallery-note"' in html


def test_overlay_draws_at_projected_pose():
    rgb = np.zeros((H, W, 3), np.uint8)
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    img = overlays.draw_overlay(rgb, K, pts, [(_T(np.eye(3), [0, 0, 1.0]), (255, 0, 0))], out_height=H)
    assert img.shape[0] == H and img[..., 0].max() == 255 and img[..., 1].max() == 0


def test_report_without_ground_truth(tmp_path):
    run = make_run(tmp_path, with_gt=False)
    out = report_stage.main(None, None, run)
    s = pd.read_csv(out / "summary.csv").set_index("obj_name")
    # obj_a: 3 ok of 4 rows; obj_b: 3 of 3 (its missing frame has no row); all: 6 / 7.
    assert s.loc["obj_a", "detection_rate_pct"] == pytest.approx(75.0)
    assert s.loc["obj_b", "detection_rate_pct"] == pytest.approx(100.0)
    assert s.loc["all", "detection_rate_pct"] == pytest.approx(600 / 7)
    assert s.loc["obj_a", "median_confidence"] == pytest.approx(0.7)
    assert len(pd.read_csv(out / "frames.csv")) == 7
    html = (out / "index.html").read_text()
    imgs = _imgs(html)
    assert "plot-confidence" in imgs and 'id="results-table"' in html
    if HAVE_DATASETS:
        assert sum(k.startswith("overlay-most-confident") for k in imgs) == 4
        assert sum(k.startswith("overlay-least-confident") for k in imgs) == 2


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


def _run_browser(browser: str, tmp: Path, *args: str) -> subprocess.CompletedProcess:
    flags = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        f"--user-data-dir={tmp / 'profile'}",
        "--enable-logging=stderr",
        "--v=0",
    ]
    return subprocess.run([browser, *flags, *args], check=False, capture_output=True, text=True, timeout=180)


def _console_errors(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ":CONSOLE" in ln or "Uncaught" in ln]


@pytest.mark.slow
def test_report_in_browser(report, chromium, tmp_path):
    url = (report / "index.html").resolve().as_uri()
    dom = _run_browser(chromium, tmp_path, "--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    assert not _console_errors(dom.stderr)
    assert '<table id="results-table"' in dom.stdout
    imgs = _imgs(dom.stdout)  # the parsed DOM: every image kept its id, alt and inline PNG
    assert {"plot-curve-adds", "plot-curve-add", "plot-errors", "plot-confidence"} <= set(imgs)
    assert all(len(b64) > 1000 for b64 in imgs.values())

    shot = tmp_path / "report.png"
    res = _run_browser(chromium, tmp_path, f"--screenshot={shot}", "--window-size=1280,2600", "--hide-scrollbars", url)
    assert res.returncode == 0 and shot.is_file(), res.stderr[-2000:]
    assert not _console_errors(res.stderr)
    img = cv2.imread(str(shot))
    assert img.shape[:2] == (2600, 1280)
    assert img.std() > 20, "screenshot looks blank"
    # The page is not just white: plots fill a good part of it.
    assert (img.mean(axis=2) < 200).mean() > 0.02
    if os.environ.get("BATCHPOSE_KEEP_SCREENSHOT"):
        shutil.copy(shot, os.environ["BATCHPOSE_KEEP_SCREENSHOT"])


def test_timeline_shows_each_pairs_status_and_the_most_severe_per_column():
    rows = pd.DataFrame(
        {
            "status": ["ok", "ok", "ok", "low_confidence", "hidden", "pnp_failed", "ok"],
            "tracked": [False, True, None, False, False, False, False],
        }
    )
    wrong = np.array([False, False, False, False, False, False, True])
    kinds = figures.timeline_kinds(rows, wrong)
    names = [figures.TIMELINE_KINDS[k][0] for k in kinds]
    assert names == [
        "ok, full estimate",
        "ok, tracked",
        "ok, full estimate",
        "low confidence",
        "hidden",
        "failed",
        "ok but wrong (ADD-S > 0.1 d)",
    ]
    # Two objects over 0..3 s in 2 columns: a column shows its most severe pair, white (-1) where none.
    t = np.array([0.0, 1.0, 2.0, 3.0, 0.0])
    obj = np.array(["a", "a", "a", "a", "b"])
    kind = np.array([5, 1, 4, 5, 3])
    grid = figures.timeline_grid(t, obj, kind, ["a", "b"], columns=2)
    np.testing.assert_array_equal(grid, [[1, 4], [3, -1]])


def test_timeline_section_in_both_reports(report, tmp_path):
    assert "plot-timeline" in _imgs((report / "index.html").read_text())
    out = report_stage.main(None, None, make_run(tmp_path, with_gt=False))
    html = (out / "index.html").read_text()
    assert 'id="timeline"' in html and "confidence of the ok poses" in html
    assert _decodes(_imgs(html)["plot-timeline"]).shape[1] >= 900

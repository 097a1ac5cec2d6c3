"""Frame-to-frame tracking (batchpose.method.track): a rendered clip of the bundled cracker box moving smoothly
over a fixed background, run through PoseEstimator.estimate_frame as a batch worker would."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from batchpose.config import EstimatorConfig, TrackConfig, load_estimator_config
from batchpose.core.frames import Camera, Frame
from batchpose.core.poses import PoseRecord
from batchpose.errors import ConfigError
from batchpose.method.estimator import PoseEstimator
from batchpose.method.render import get_renderer
from batchpose.method.score import FrameEdges
from batchpose.method.sequence import Sequence
from batchpose.method.track import TrackResult, view_turn_deg
from batchpose.method.tracked import refresh, seed_track
from batchpose.method.views import look_at
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import add_error, textured_background

PERIOD_NS = 33_333_333


def clip_pose(i: int, center: np.ndarray) -> np.ndarray:
    """Frame i of a smooth path: 3 degrees of azimuth and 4 mm closer per frame, a slow roll."""
    az = np.deg2rad(30.0 + 3.0 * i)
    el = np.deg2rad(25.0)
    dist = 0.75 - 0.004 * i
    eye = center + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T = look_at(eye, center, np.array([0.0, 0.0, 1.0]))
    roll = np.deg2rad(1.0 * i)
    Rz = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
    T[:3, :3] = Rz @ T[:3, :3]
    T[:3, 3] = Rz @ T[:3, 3]
    T[0, 3] += 0.002 * i
    return T


def frame_of(rgb: np.ndarray, im_id: int, scene_id: int = 0, stamp_ns: int | None = None) -> Frame:
    return Frame(
        frame_id=f"clip/{im_id}",
        scene_id=scene_id,
        im_id=im_id,
        stamp_ns=im_id * PERIOD_NS if stamp_ns is None else stamp_ns,
        camera=Camera(K_SYN, 640, 480),
        image_format="rgb8",
        image_data=np.ascontiguousarray(rgb).tobytes(),
    )


@pytest.fixture(scope="module")
def clip(cracker_model):
    """12 frames (RGB, true pose) of the moving box over one background, with sensor noise."""
    rng = np.random.default_rng(11)
    bg = textured_background(rng)
    out = []
    for i in range(12):
        T = clip_pose(i, cracker_model.center_m)
        rgb, depth = get_renderer().render(cracker_model.content_hash, cracker_model.mesh, T, K_SYN, 640, 480, "lit")
        img = bg.copy()
        img[depth > 0] = rgb[depth > 0]
        img = np.clip(img.astype(np.float32) + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
        out.append((img, T))
    return out


def make_estimator(model, library, presence_votes: int | None = None, **track) -> PoseEstimator:
    """The default estimator of one object with these ``track`` settings (and ``match.presence_votes``)."""
    conf = dataclasses.replace(EstimatorConfig(), track=TrackConfig(**track))
    if presence_votes is not None:
        conf = dataclasses.replace(conf, match=dataclasses.replace(conf.match, presence_votes=presence_votes))
    return PoseEstimator(conf, {model.name: library}, models={model.name: model}, renderer=get_renderer())


def run_clip(est: PoseEstimator, frames: list[Frame], name: str):
    seq = Sequence()
    return [est.estimate_frame(f, [name], seq)[0] for f in frames]


def test_tracked_poses_follow_the_object(cracker_model, cracker_library, clip):
    est = make_estimator(cracker_model, cracker_library)
    recs = run_clip(est, [frame_of(img, i) for i, (img, _) in enumerate(clip)], cracker_model.name)
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    errors = [add_error(r.cam_from_model, T, pts) for r, (_, T) in zip(recs, clip, strict=True)]
    print("ADD mm", np.round(np.array(errors) * 1000, 2), "tracked", [r.tracked for r in recs])
    assert not recs[0].tracked and all(r.tracked for r in recs[1:])
    assert all(r.ok for r in recs)
    # Tracked frames skip SIFT and matching: no time is booked on those stages.
    assert all("sift" not in r.timings and "match" not in r.timings and r.timings["track"] > 0 for r in recs[1:])
    assert "seed" in recs[0].timings
    # 11 frames of flow (3 degrees and 4 mm closer a frame) do not drift: every tracked pose within 2 % of
    # the box's diameter (5 mm; a full estimate is within ~1 mm here, ADD's threshold is 27 mm).
    assert max(errors[1:]) < 0.02 * cracker_model.diameter_m, errors
    assert all(0 < r.confidence <= recs[0].confidence for r in recs[1:])


def test_render_anchoring_removes_flow_drift(cracker_model, cracker_library, clip):
    """track.render_every = 1: every tracked frame is pulled back onto the mesh rendered at its pose, so
    the tracked poses are as close as a full estimate (< 1 mm ADD here; flow alone drifts to ~3 mm)."""
    est = make_estimator(cracker_model, cracker_library, render_every=1)
    recs = run_clip(est, [frame_of(img, i) for i, (img, _) in enumerate(clip)], cracker_model.name)
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    errors = [add_error(r.cam_from_model, T, pts) for r, (_, T) in zip(recs, clip, strict=True)]
    assert all(r.tracked for r in recs[1:])
    assert max(errors[1:]) < 0.001, errors


def test_refresh_keeps_a_true_track_and_ends_a_drifted_one(cracker_model, cracker_library, clip):
    """A refresh (track.refresh_every) re-seeds a track whose pose matches the mesh in the frame, and ends
    one that has drifted farther than the NCC search reaches (here: 2 cm sideways, ~20 px)."""
    from batchpose.method.track import TrackResult

    est = make_estimator(cracker_model, cracker_library)
    cam = Camera(K_SYN, 640, 480)
    img, T = clip[3]
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    from batchpose.core.poses import PoseRecord

    start = seed_track(
        est.objects, cracker_model.name, gray, PoseRecord("", cracker_model.name, "ok", cam_from_model=T), cam
    )
    start.age = 32
    kept = refresh(est.objects, cracker_model.name, gray, TrackResult(start, len(start.xy), 0.1), cam)
    assert kept is not None and kept.track.age == 0 and len(kept.track.xy) >= 50
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    assert add_error(kept.track.cam_from_model, T, pts) < 0.001
    drifted = dataclasses.replace(start, cam_from_model=T.copy())
    drifted.cam_from_model[0, 3] += 0.02
    assert refresh(est.objects, cracker_model.name, gray, TrackResult(drifted, len(start.xy), 0.1), cam) is None


@pytest.mark.parametrize(
    ("change", "expect"),
    [
        ("im_id_gap", [False, True, True, False, True, True]),  # frame 3 is im_id 4: a skipped image
        ("scene", [False, True, True, False, True, True]),  # frame 3 starts another scene
        ("time_gap", [False, True, True, False, True, True]),  # frame 3 comes 1 s later
        ("redetect_every_2", [False, True, True, False, True, True]),  # two tracked frames, then afresh
        ("low_confidence", [False] * 6),  # no estimate is confident enough to start a track
        ("disabled", [False] * 6),
    ],
)
def test_when_a_track_starts_and_ends(cracker_model, cracker_library, clip, change, expect):
    track = {"redetect_every": 2} if change == "redetect_every_2" else {}
    if change == "low_confidence":
        track["min_confidence"] = 1.01
    if change == "disabled":
        track["enabled"] = False
    est = make_estimator(cracker_model, cracker_library, **track)
    frames = []
    for i, (img, _) in enumerate(clip[:6]):
        im_id, scene, stamp = i, 0, None
        if i >= 3 and change == "im_id_gap":
            im_id = i + 1
        if i >= 3 and change == "scene":
            scene = 1
        if i >= 3 and change == "time_gap":
            stamp = i * PERIOD_NS + 1_000_000_000
        frames.append(frame_of(img, im_id, scene, stamp))
    recs = run_clip(est, frames, cracker_model.name)
    assert [r.tracked for r in recs] == expect
    assert all(r.ok for r in recs)


def test_tracking_follows_every_other_frame_of_a_selection(cracker_model, cracker_library, clip):
    """A manifest's ``frames.every: 2`` keeps im_ids 0, 2, 4, 6 with ``im_step`` 2: tracked from one kept
    frame to the next. Without the step the same frames are a gap each time: every one estimated afresh."""
    est = make_estimator(cracker_model, cracker_library)
    frames = [frame_of(img, i) for i, (img, _) in enumerate(clip[:8])][::2]
    stepped = run_clip(est, [dataclasses.replace(f, im_step=2) for f in frames], cracker_model.name)
    assert [r.tracked for r in stepped] == [False, True, True, True]
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    assert all(add_error(r.cam_from_model, clip[2 * i][1], pts) < 0.005 for i, r in enumerate(stepped))
    assert [r.tracked for r in run_clip(est, frames, cracker_model.name)] == [False] * 4


def test_view_turn_counts_moves_around_the_object_not_rolls():
    T = clip_pose(0, np.zeros(3))
    roll = np.eye(4)
    roll[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.0, 0.7]))[0]  # about the optical axis
    assert view_turn_deg(T, roll @ T) < 1e-3
    view = -T[:3, :3].T @ T[:3, 3]  # the camera as seen from the object
    axis = np.cross(view, [0.0, 0.0, 1.0])
    turn = np.eye(4)
    turn[:3, :3] = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.deg2rad(25.0))[0]  # the object turned 25 deg
    assert view_turn_deg(T, T @ turn) == pytest.approx(25.0, abs=1e-6)
    spin = np.eye(4)
    spin[:3, :3] = cv2.Rodrigues(view / np.linalg.norm(view) * 1.0)[0]  # about the line of sight itself
    assert view_turn_deg(T, T @ spin) < 1e-3


def test_a_track_refreshes_when_the_view_has_turned(cracker_model, cracker_library, clip):
    """The clip turns 3 degrees a frame: with ``refresh_turn_deg`` 20 the track is refreshed (a render and a
    seeding: time on ``seed``) once the camera has gone 20 degrees around the box, long before 32 frames."""
    refreshed = {}
    for turn in (20.0, 0.0):
        est = make_estimator(cracker_model, cracker_library, refresh_turn_deg=turn)
        recs = run_clip(est, [frame_of(img, i) for i, (img, _) in enumerate(clip)], cracker_model.name)
        assert all(r.tracked for r in recs[1:])
        refreshed[turn] = [i for i, r in enumerate(recs) if i and r.timings.get("seed", 0) > 0]
    assert refreshed[0.0] == [] and refreshed[20.0] and refreshed[20.0][0] in (7, 8)


def test_a_pose_the_frame_does_not_look_like_starts_no_track(cracker_model, cracker_library, clip):
    """``track.min_match``: a confident but wrong full estimate (the box turned 40 degrees) is not followed,
    and a refresh at a pose that has turned away from the frame ends the track; at the true pose both go on."""
    img, T = clip[0]
    cam = Camera(K_SYN, 640, 480)
    gray, lab = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), FrameEdges(img)
    turned = T.copy()
    turned[:3, :3] = T[:3, :3] @ cv2.Rodrigues(np.array([0.0, 0.0, np.deg2rad(40.0)]))[0]
    name = cracker_model.name
    for min_match, pose, expect in ((0.35, T, True), (0.35, turned, False), (0.0, turned, True)):
        est = make_estimator(cracker_model, cracker_library, min_match=min_match)
        rec = PoseRecord("", name, "ok", cam_from_model=pose, confidence=0.9)
        track = seed_track(est.objects, name, gray, rec, cam, (), lab)
        assert (track is not None) == expect, (min_match, expect)
    est = make_estimator(cracker_model, cracker_library)
    start = seed_track(
        est.objects, name, gray, PoseRecord("", name, "ok", cam_from_model=T, confidence=0.9), cam, (), lab
    )
    assert refresh(est.objects, name, gray, TrackResult(start, len(start.xy), 0.1), cam, (), lab) is not None
    wrong = dataclasses.replace(start, cam_from_model=turned)
    assert refresh(est.objects, name, gray, TrackResult(wrong, len(start.xy), 0.1), cam, (), lab) is None


def test_tracking_with_lens_distortion(cracker_model, cracker_library, clip):
    """The clip seen through a lens with barrel distortion (k1 = -0.25): seeding looks the depth up at the
    undistorted position and flow works in the distorted image; tracked poses stay within 1 % of the
    diameter (1.5 mm here; looking the depth up at the distorted position instead gives 3.4-3.9 mm)."""
    dist = np.array([-0.25, 0.05, 0.0, 0.0, 0.0])
    h, w = 480, 640
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), axis=-1).reshape(-1, 1, 2).astype(np.float64)
    src = cv2.undistortPoints(grid, K_SYN, dist, P=K_SYN).reshape(h, w, 2).astype(np.float32)
    frames = []
    for i, (img, _) in enumerate(clip[:6]):
        seen = cv2.remap(img, src[..., 0], src[..., 1], cv2.INTER_LINEAR)  # pinhole image -> distorted
        frames.append(dataclasses.replace(frame_of(seen, i), camera=Camera(K_SYN, 640, 480, dist=dist)))
    est = make_estimator(cracker_model, cracker_library)
    recs = run_clip(est, frames, cracker_model.name)
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    errors = [add_error(r.cam_from_model, T, pts) for r, (_, T) in zip(recs, clip[:6], strict=False)]
    assert [r.tracked for r in recs] == [False] + [True] * 5
    assert max(errors) < 0.01 * cracker_model.diameter_m, errors


def test_a_cut_is_not_tracked(cracker_model, cracker_library, clip):
    """A cut to another view of the object (next im_id, as in a spliced log): the flow check loses the
    track and the frame is estimated afresh, correctly."""
    est = make_estimator(cracker_model, cracker_library)
    order = [0, 1, 2, 9, 10]  # frames 9 and 10 show the box 21-24 degrees on, 3 cm closer
    recs = run_clip(est, [frame_of(clip[j][0], i) for i, j in enumerate(order)], cracker_model.name)
    assert [r.tracked for r in recs] == [False, True, True, False, True]
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    assert add_error(recs[3].cam_from_model, clip[9][1], pts) < 0.02 * cracker_model.diameter_m


@pytest.mark.parametrize("min_ncc", [0.5, -1.0])
def test_corners_on_an_occluder_are_not_seeded(cracker_model, cracker_library, clip, min_ncc):
    """A textured card held still in front of the moving box: (almost) no corner is seeded on it (with the
    check turned off, min_ncc = -1, many are), and the tracked poses follow the box, not the card."""
    rng = np.random.default_rng(3)
    card = textured_background(rng, 70, 90)
    x0, y0 = 300, 200  # over the middle of the box in every frame
    frames = []
    for i, (img, _) in enumerate(clip[:6]):
        img = img.copy()
        img[y0 : y0 + 90, x0 : x0 + 70] = card
        frames.append(frame_of(img, i))
    est = make_estimator(cracker_model, cracker_library, min_ncc=min_ncc)
    seq = Sequence()
    first = est.estimate_frame(frames[0], [cracker_model.name], seq)[0]
    assert first.ok and not first.tracked
    key = seq.tracks[cracker_model.name].key_xy
    inside = (key[:, 0] >= x0 + 4) & (key[:, 0] < x0 + 66) & (key[:, 1] >= y0 + 4) & (key[:, 1] < y0 + 86)
    print(f"min_ncc {min_ncc}: {inside.sum()} of {len(key)} seeded corners inside the card")
    if min_ncc < 0:
        assert inside.sum() >= 5  # the card is textured: without the check its corners are seeded
        return
    assert len(key) >= 30 and inside.sum() <= 2
    recs = [est.estimate_frame(f, [cracker_model.name], seq)[0] for f in frames[1:]]
    assert all(r.tracked for r in recs)
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    errors = [add_error(r.cam_from_model, T, pts) for r, (_, T) in zip(recs, clip[1:6], strict=False)]
    assert max(errors) < 0.02 * cracker_model.diameter_m, errors


def test_unreadable_frame_breaks_the_track(cracker_model, cracker_library, clip):
    est = make_estimator(cracker_model, cracker_library)
    frames = [frame_of(img, i) for i, (img, _) in enumerate(clip[:4])]
    frames[2] = dataclasses.replace(frames[2], image_data=b"")
    recs = run_clip(est, frames, cracker_model.name)
    assert [r.status for r in recs] == ["ok", "ok", "bad_image", "ok"]
    assert [r.tracked for r in recs] == [False, True, False, False]


def test_track_config_is_checked():
    with pytest.raises(ConfigError, match="track.min_points must be >= 6"):
        load_estimator_config({"track": {"min_points": 2}})
    with pytest.raises(ConfigError, match="unknown key pointz"):
        load_estimator_config({"track": {"pointz": 2}})
    with pytest.raises(ConfigError, match="track.lost_full_every must be >= 1"):
        load_estimator_config({"track": {"lost_full_every": 0}})
    with pytest.raises(ConfigError, match="track.occlusion_margin_px must be >= -1"):
        load_estimator_config({"track": {"occlusion_margin_px": -2}})
    with pytest.raises(ConfigError, match="track.hidden_above must be in \\(0, 1\\]"):
        load_estimator_config({"track": {"hidden_above": 0}})
    with pytest.raises(ConfigError, match="track.hidden_quick"):
        load_estimator_config({"track": {"hidden_quick": "yes"}})
    with pytest.raises(ConfigError, match="track.hidden_retry"):
        load_estimator_config({"track": {"hidden_retry": 1}})
    with pytest.raises(ConfigError, match="retry_contrast_threshold must be 0 \\(off\\) or below"):
        load_estimator_config({"features": {"retry_contrast_threshold": 0.03}})
    with pytest.raises(ConfigError, match="retry_sigma must be 0 \\(off\\) or positive, got -1"):
        load_estimator_config({"features": {"retry_sigma": -1}})
    with pytest.raises(ConfigError, match="strong_inliers must be >= 0"):
        load_estimator_config({"strong_inliers": -1})


def test_seed_lifts_corners_onto_the_surface(cracker_model, clip):
    """Seeded corners' 3D points reproject onto the corners (the lift is exact at the true pose)."""
    from batchpose.method.track import seed

    img, T = clip[0]
    rgb, depth = get_renderer().render(cracker_model.content_hash, cracker_model.mesh, T, K_SYN, 640, 480)
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    xy, X = seed(gray, T, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), depth, K_SYN, np.zeros(0), TrackConfig())
    assert 50 <= len(xy) <= TrackConfig().points
    proj, _ = cv2.projectPoints(X, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K_SYN, None)
    assert np.median(np.linalg.norm(proj.reshape(-1, 2) - xy, axis=1)) < 0.6
    assert np.all(depth[np.rint(xy[:, 1]).astype(int), np.rint(xy[:, 0]).astype(int)] > 0)


def test_tracks_flowed_together_move_as_they_would_alone(cracker_model, clip):
    """follow_all flows every track's points in shared calls: two tracks (the seeded corners split in
    halves, one keyframe) end exactly where following each alone puts them, and on the true pose."""
    from batchpose.method.track import Track, follow, follow_all, seed

    (img0, T0), (img1, T1) = clip[0], clip[1]
    rgb, depth = get_renderer().render(cracker_model.content_hash, cracker_model.mesh, T0, K_SYN, 640, 480)
    g0, g1 = (cv2.cvtColor(i, cv2.COLOR_RGB2GRAY) for i in (img0, img1))
    conf = TrackConfig()
    xy, X = seed(g0, T0, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), depth, K_SYN, np.zeros(0), conf)
    h = len(xy) // 2
    tracks = [
        Track(xy[s], X[s], T0, len(xy[s]), 0.9, key_gray=g0, key_xy=xy[s].copy()) for s in (slice(0, h), slice(h, None))
    ]
    together = follow_all(g0, g1, tracks, K_SYN, np.zeros(0), conf)
    alone = [follow(g0, g1, t, K_SYN, np.zeros(0), conf) for t in tracks]
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    for a, b in zip(together, alone, strict=True):
        assert a is not None and b is not None and a.n_inliers == b.n_inliers
        np.testing.assert_allclose(a.track.cam_from_model, b.track.cam_from_model, atol=1e-9)
        np.testing.assert_allclose(a.track.xy, b.track.xy, atol=1e-4)
        assert add_error(a.track.cam_from_model, T1, pts) < 0.01 * cracker_model.diameter_m


@pytest.mark.slow
def test_tracked_run_is_the_same_with_2_jobs_and_after_a_resume(cracker_model, clip, tmp_path, cache_dir, stop_run):
    """The whole job on a 10-frame MCAP of the clip, in tasks of 4 frames: --jobs 1, --jobs 2 and a run
    stopped after its first task or inside its second and resumed give the same poses and tracked flags."""
    import pandas as pd

    from batchpose import run
    from batchpose.core.frames import ObjectPose
    from batchpose.io.mcap_write import write_frames_mcap
    from tests.conftest import ROOT

    frames = [
        dataclasses.replace(frame_of(img, i), gt=(ObjectPose(cracker_model.name, T),))
        for i, (img, T) in enumerate(clip[:10])
    ]
    log = tmp_path / "clip.mcap"
    write_frames_mcap(frames, log, obj_ids={cracker_model.name: 2})
    manifest = tmp_path / "clip.yaml"
    manifest.write_text(
        f"name: clip\nframes: {{format: mcap, path: {log}}}\n"
        f"models: {{root: {ROOT / 'demo_data' / 'models'}, mesh: '{{name}}/textured.obj'}}\n"
        f"objects: [{cracker_model.name}]\ntargets: all\n"
    )
    pipeline, small = ROOT / "pipelines" / "gnc_pose.yaml", ["track.chunk_frames=4", "track.min_chunks=1"]

    def poses(out):
        df = pd.read_parquet(out / "poses.parquet").sort_values("im_id").reset_index(drop=True)
        return df[["im_id", "status", "tracked"]], np.stack(df["R"]), np.stack(df["t_m"])

    runs = {}
    for jobs in (1, 2):
        out = run.main(
            pipeline, manifest, tmp_path / f"j{jobs}", cache_dir=cache_dir, overrides=small, jobs=jobs, report=False
        )
        runs[jobs] = poses(out)
    # Killed after the first task of 4 frames, and killed inside a task (saved after each frame: the rerun
    # starts from the tracks saved with the third frame): both resume to the same poses.
    for name, stop in (("resumed", {"after": 1}), ("resumed_mid_task", {"after": 6, "at": "save"})):
        resumed = tmp_path / name
        stop_run(**stop)
        with pytest.raises(stop_run.Stopped):
            run.main(pipeline, manifest, resumed, cache_dir=cache_dir, overrides=small, jobs=1, report=False)
        stop_run.disarm()
        assert not (resumed / "poses.parquet").exists()
        run.main(pipeline, manifest, resumed, cache_dir=cache_dir, overrides=small, jobs=1, report=False)
        runs[name] = poses(resumed)
        assert not list((resumed / "shards").glob("chunk-*.state"))  # every task finished: no state left
    flags, R, t = runs[1]
    # Each task of 4 frames starts with a full estimate and tracks the rest.
    assert flags["tracked"].tolist() == [i % 4 != 0 for i in range(10)]
    assert (flags["status"] == "ok").all()
    for other in (runs[2], runs["resumed"], runs["resumed_mid_task"]):
        pd.testing.assert_frame_equal(other[0], flags)
        np.testing.assert_allclose(other[1], R, atol=1e-9)
        np.testing.assert_allclose(other[2], t, atol=1e-9)


@pytest.mark.parametrize("lost_full_every", [4, 1])
def test_an_object_that_stays_lost_gets_quick_estimates_between_full_ones(
    cracker_model, cracker_library, clip, lost_full_every
):
    """Six frames of background without the box, then the box: while it stays lost only every 4th frame
    gets the full estimate (its fine pass), the others the quick one; it is found and tracked when it
    shows. With track.lost_full_every = 1 every frame gets the full estimate. (Without the presence check,
    which makes the box ``absent`` in the background frames at once: as under ``targets: annotations``.)"""
    bg = textured_background(np.random.default_rng(5))
    frames = [frame_of(bg, i) for i in range(6)] + [frame_of(clip[j][0], 6 + j) for j in range(3)]
    est = make_estimator(cracker_model, cracker_library, presence_votes=0, lost_full_every=lost_full_every)
    recs = run_clip(est, frames, cracker_model.name)
    full = [("fine" in r.timings) for r in recs[:6]]
    assert full == ([True, False, False, False, True, False] if lost_full_every == 4 else [True] * 6)
    assert [r.ok for r in recs[6:]] == [True] * 3 and [r.tracked for r in recs[6:]] == [False, True, True]
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    assert add_error(recs[6].cam_from_model, clip[0][1], pts) < 0.02 * cracker_model.diameter_m


def gelatin_pose(x: float, z: float) -> np.ndarray:
    """The gelatin box, turned, at (x, 0, z) in the camera frame."""
    G = np.eye(4)
    G[:3, :3] = cv2.Rodrigues(np.array([0.3, 0.5, 0.2]))[0]
    G[:3, 3] = [x, 0.0, z]
    return G


def two_boxes(cracker_model, T: np.ndarray, gelatin, G: np.ndarray, bg: np.ndarray, rng):
    """The cracker box at T and the gelatin box at G (in front) over ``bg``, with sensor noise: (RGB, the
    cracker's depth, the gelatin box's depth)."""
    renderer = get_renderer()
    rgb, depth = renderer.render(cracker_model.content_hash, cracker_model.mesh, T, K_SYN, 640, 480, "lit")
    rgb_g, depth_g = renderer.render(gelatin.content_hash, gelatin.mesh, G, K_SYN, 640, 480, "lit")
    img = bg.copy()
    img[depth > 0] = rgb[depth > 0]
    img[depth_g > 0] = rgb_g[depth_g > 0]
    img = np.clip(img.astype(np.float32) + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    return img, depth, depth_g


def test_points_hidden_by_a_tracked_object_in_front_are_dropped(cracker_model):
    """The gelatin box slides in front of the (almost still) cracker box until half of it is hidden. With the
    gelatin box as an occluder (``track.occluders`` at its previous pose, as the estimator passes it), the
    cracker's points it covers are dropped and count as never seeded: the track lives through all 15
    frames on the true pose and keeps no point on the gelatin box. Without, those points are dragged along
    or fail and the track ends."""
    from batchpose.io.mesh import load_mesh
    from batchpose.method.track import Track, follow_all, occluders, seed
    from tests.conftest import GELATIN

    gelatin = load_mesh(GELATIN)
    renderer, rng = get_renderer(), np.random.default_rng(11)
    bg = textured_background(rng)
    grays, boxes, gels, gel_depths = [], [], [], []
    for i in range(16):
        T = clip_pose(0, cracker_model.center_m)
        T[0, 3] += 0.0005 * i
        G = gelatin_pose(-0.09 + 0.005 * i, 0.45)  # in front of the box, ~9 px a frame to the right
        img, depth, depth_g = two_boxes(cracker_model, T, gelatin, G, bg, rng)
        grays.append(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
        boxes.append(T)
        gels.append(G)
        gel_depths.append(depth_g)
    assert ((gel_depths[15] > 0) & (depth > 0)).sum() > 0.4 * (depth > 0).sum()  # the last frame hides ~half

    conf = TrackConfig()
    rgb, depth = renderer.render(cracker_model.content_hash, cracker_model.mesh, boxes[0], K_SYN, 640, 480)
    xy, X = seed(grays[0], boxes[0], cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), depth, K_SYN, np.zeros(0), conf)
    hulls = [np.asarray(m.mesh.convex_hull.vertices) for m in (cracker_model, gelatin)]
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    for use in (True, False):
        track = Track(xy, X, boxes[0], len(xy), 0.9, key_gray=grays[0], key_xy=xy.copy())
        errors = []
        for i in range(1, 16):
            hidden = None
            if use:
                poses = [track.cam_from_model, gels[i - 1]]
                hidden = occluders(hulls, poses, K_SYN, np.zeros(0), 640, 480, conf.occlusion_margin_px)[:1]
            res = follow_all(grays[i - 1], grays[i], [track], K_SYN, np.zeros(0), conf, hidden)[0]
            if res is None:
                break
            track = res.track
            errors.append(add_error(track.cam_from_model, boxes[i], pts))
        print(f"occluders {use}: {len(errors)} frames tracked, {len(track.xy)} points of {track.n_seeded} seeded")
        if not use:
            assert len(errors) < 15  # the track ends
            continue
        assert len(errors) == 15 and max(errors) < 0.005 * cracker_model.diameter_m, errors
        assert track.n_seeded < len(xy) and len(track.xy) >= conf.min_fraction * track.n_seeded
        on_gelatin = gel_depths[15][np.rint(track.xy[:, 1]).astype(int), np.rint(track.xy[:, 0]).astype(int)] > 0
        assert not on_gelatin.any()


def test_an_object_whose_track_dies_young_still_counts_as_lost(cracker_model, cracker_library, clip):
    """The box is found and tracked in one frame, then gone: its track dies a frame old, and the estimates
    that follow are quick ones with the full one every 4th frame, counted from the frame it was last
    estimated afresh (a mostly hidden object's short tracks would otherwise make every estimate a full one).
    Without the presence check, as under ``targets: annotations``."""
    bg = textured_background(np.random.default_rng(5))
    frames = [frame_of(clip[0][0], 0), frame_of(clip[1][0], 1)] + [frame_of(bg, i) for i in range(2, 8)]
    est = make_estimator(cracker_model, cracker_library, presence_votes=0)
    recs = run_clip(est, frames, cracker_model.name)
    assert [r.ok for r in recs[:2]] == [True, True] and [r.tracked for r in recs[:2]] == [False, True]
    assert not any(r.ok for r in recs[2:])
    # lost count 1 at the seeding, 2 after the tracked frame: full estimates at counts 4 and 8
    assert [("fine" in r.timings) for r in recs[2:]] == [False, False, True, False, False, False]


def test_covered_counts_only_what_is_in_front(cracker_model):
    """track.covered: the gelatin box's projected hull in front of the cracker box covers part of it; the same
    box behind it covers nothing; off to the side, nothing."""
    from batchpose.io.mesh import load_mesh
    from batchpose.method.track import covered
    from tests.conftest import GELATIN

    gelatin = load_mesh(GELATIN)
    hull_c = np.asarray(cracker_model.mesh.convex_hull.vertices)
    hull_g = np.asarray(gelatin.mesh.convex_hull.vertices)
    T = clip_pose(0, cracker_model.center_m)
    G = np.eye(4)
    G[:3, 3] = [T[0, 3], T[1, 3], 0.35]  # on the box's line of sight, in front
    frac, each = covered(hull_c, T, [(hull_g, G)], K_SYN, np.zeros(0), 640, 480)
    assert 0.3 < frac < 1 and each == [frac]
    behind = G.copy()
    behind[2, 3] = T[2, 3] + 0.3
    assert covered(hull_c, T, [(hull_g, behind)], K_SYN, np.zeros(0), 640, 480) == (0.0, [0.0])
    aside = G.copy()
    aside[0, 3] += 0.5
    both = covered(hull_c, T, [(hull_g, aside), (hull_g, G)], K_SYN, np.zeros(0), 640, 480)
    assert both[0] == frac and both[1] == [0.0, frac]
    # Mostly off the image (leaving the view): nothing hides it, even with the box in front of what is left.
    gone, in_front = T.copy(), G.copy()
    gone[0, 3] += T[2, 3] * 320 / K_SYN[0, 0] + 0.05
    in_front[0, 3] = gone[0, 3] * 0.35 / T[2, 3]
    assert covered(hull_c, gone, [(hull_g, in_front)], K_SYN, np.zeros(0), 640, 480) == (0.0, [0.0])
    partly, front = gone.copy(), in_front.copy()  # 85 % in view (gone: 21 %), the box in front of it
    partly[0, 3] -= 0.1
    front[0, 3] = partly[0, 3] * 0.35 / T[2, 3] - 0.02
    assert covered(hull_c, partly, [(hull_g, front)], K_SYN, np.zeros(0), 640, 480)[0] > 0.3


@pytest.fixture(scope="module")
def gelatin_library(cache_dir):
    from batchpose.io import library
    from batchpose.io.mesh import load_mesh
    from batchpose.stages import build_templates
    from tests.conftest import GELATIN

    gelatin = load_mesh(GELATIN)
    return gelatin, library.load(build_templates.build_library(gelatin, EstimatorConfig(), K_SYN, 640, 480, cache_dir))


@pytest.mark.parametrize(("hidden_above", "hidden_quick"), [(0.6, True), (0.6, False), (1.0, True)])
def test_a_lost_object_mostly_behind_a_tracked_one_is_reported_hidden(
    cracker_model, cracker_library, gelatin_library, hidden_above, hidden_quick, monkeypatch
):
    """The gelatin box (tracked) passes in front of the still cracker box, hiding up to ~95 % of it, and on.
    The cracker's track ends; while the gelatin box covers >= 60 % of it at its last pose, the frames that
    would get a quick estimate report it ``hidden``, naming the gelatin box; once less is covered it is
    found again and tracked. Every confident pose is right. With track.hidden_above = 1 every frame is
    estimated. The estimates it still gets are quick ones by default (track.hidden_quick), full ones with
    hidden_quick false; either way none is given the low-contrast retry."""
    gelatin, gel_lib = gelatin_library
    renderer, rng = get_renderer(), np.random.default_rng(11)
    bg = textured_background(rng)
    T = clip_pose(0, cracker_model.center_m)
    frames, visible = [], []
    for i in range(30):
        G = gelatin_pose(-0.12 + 0.006 * i, 0.3)  # in front of the box, ~16 px a frame to the right
        img, depth, depth_g = two_boxes(cracker_model, T, gelatin, G, bg, rng)
        frames.append(frame_of(img, i))
        visible.append(((depth > 0) & (depth_g == 0)).sum() / (depth > 0).sum())
    assert min(visible) < 0.1 and visible[0] == 1.0 and visible[-1] > 0.7
    track = TrackConfig(hidden_above=hidden_above, hidden_quick=hidden_quick)
    conf = dataclasses.replace(EstimatorConfig(), track=track)
    unretried, hidden_and_quick = [], []

    from batchpose.method import tracked

    fresh_estimate = tracked.estimate_image

    def watched(*args, quick=frozenset(), no_retry=frozenset(), **kwargs):
        """Records which objects the tracker spares the retry, and which are quick."""
        unretried.extend(no_retry)
        hidden_and_quick.extend((name, name in quick) for name in no_retry)
        return fresh_estimate(*args, quick=quick, no_retry=no_retry, **kwargs)

    monkeypatch.setattr(tracked, "estimate_image", watched)
    est = PoseEstimator(
        conf,
        {cracker_model.name: cracker_library, gelatin.name: gel_lib},
        models={cracker_model.name: cracker_model, gelatin.name: gelatin},
        renderer=renderer,
    )
    seq = Sequence()
    recs = [est.estimate_frame(f, [cracker_model.name, gelatin.name], seq) for f in frames]
    box = [r[0] for r in recs]
    assert all(r[1].ok for r in recs) and all(r[1].tracked for r in recs[1:])
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    confident = [r for r in box if r.ok and r.confidence >= conf.track.min_confidence]
    errors = [add_error(r.cam_from_model, T, pts) / cracker_model.diameter_m for r in confident]
    print([(r.status, r.tracked, round(v, 2)) for r, v in zip(box, visible, strict=True)])
    assert max(errors) < 0.1
    hidden = [i for i, r in enumerate(box) if r.status == "hidden"]
    if hidden_above == 1.0:
        assert not hidden
    else:
        assert len(hidden) >= 2 and all(visible[i] < 0.25 for i in hidden)
        assert all(box[i].reason.endswith("behind 009_gelatin_box at its last pose; not estimated") for i in hidden)
        assert not box[hidden[0] - 1].tracked  # the track had ended: a lost object is never skipped otherwise
    # The full estimates of the mostly hidden box get no low-contrast retry (track.hidden_retry false).
    assert set(unretried) == ({cracker_model.name} if hidden_above < 1 else set())
    assert all(q == hidden_quick for _, q in hidden_and_quick)
    assert all(r.ok and r.tracked for r in box[-3:])

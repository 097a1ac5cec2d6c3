"""Coarse-to-fine keypoints and the turned (flip) hypotheses of the refinement (issue 7)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from batchpose.config import EstimatorConfig, FineConfig, RefineConfig, load_estimator_config, load_yaml
from batchpose.core.frames import Camera
from batchpose.core.geometry import rotation_error_deg
from batchpose.method.correspondences import Correspondences
from batchpose.method.estimator import PoseEstimator
from batchpose.method.features import detect, to_gray
from batchpose.method.gnc_pnp import PnpResult
from batchpose.method.hypotheses import refine
from batchpose.method.passes import fine_keypoints
from batchpose.method.render import get_renderer
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import compose, random_pose


def rot_deg(A: np.ndarray, B: np.ndarray) -> float:
    return rotation_error_deg(A[:3, :3], B[:3, :3])


def test_flips_are_half_turns_about_the_box_axes(cracker_model):
    flips = cracker_model.flips()
    assert len(flips) == 3
    tri, w = cracker_model.mesh.triangles_center, cracker_model.mesh.area_faces
    centroid = (tri * w[:, None]).sum(axis=0) / w.sum()
    axes = []
    for F in flips:
        R = F[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert rot_deg(R, np.eye(3)) == pytest.approx(180.0, abs=1e-4)
        np.testing.assert_allclose(F @ F, np.eye(4), atol=1e-9)  # a half turn undoes itself
        np.testing.assert_allclose(R @ centroid + F[:3, 3], centroid, atol=1e-9)
        w_, v = np.linalg.eigh(R)
        axes.append(v[:, np.argmax(w_)])  # eigenvalue +1: the axis
    # The bundled cracker box is modelled with its edges along the model axes: each flip turns about one.
    dots = np.abs(np.array(axes))
    assert np.all(dots.max(axis=1) > 0.98), dots
    assert sorted(dots.argmax(axis=1).tolist()) == [0, 1, 2]


def test_fine_keypoints_land_on_the_same_pixels(cracker_model):
    rng = np.random.default_rng(5)
    T = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T)
    gray = to_gray(img)
    conf = EstimatorConfig()
    xy_full, _ = detect(gray, conf.features)
    box = (200, 120, 440, 360)
    xy_up, _ = fine_keypoints(gray, box, conf)
    for up in (1.0, 2.0):
        c = dataclasses.replace(conf, fine=FineConfig(upsample=up))
        xy_f, desc_f = fine_keypoints(gray, box, c)
        assert len(xy_f) == len(desc_f) > 50
        assert np.all((xy_f >= [box[0] - 1, box[1] - 1]) & (xy_f <= [box[2], box[3]]))
    assert len(xy_up) > 1.5 * len(fine_keypoints(gray, box, dataclasses.replace(conf, fine=FineConfig(upsample=1)))[0])
    # Keypoints found at 1x well inside the box are found again at 2x, at the same place (sub-pixel).
    inner = np.all((xy_full > [box[0] + 20, box[1] + 20]) & (xy_full < [box[2] - 20, box[3] - 20]), axis=1)
    d = np.linalg.norm(xy_full[inner][:, None] - xy_up[None], axis=2).min(axis=1)
    assert inner.sum() > 20
    assert np.median(d) < 0.5, np.median(d)


@pytest.mark.parametrize("strong_inliers", [0, 20, 100000])
def test_fine_pass_is_skipped_after_a_strong_coarse_pass(cracker_model, cracker_library, strong_inliers):
    """strong_inliers: a sharp synthetic frame gives the whole-frame pass far more than 20 inliers, so
    with 20 the fine pass does not run (and only that pose is refined); with 0 (off) or an unreachable
    count it does; the pose is right either way."""
    rng = np.random.default_rng(8)
    T = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T)
    conf = dataclasses.replace(EstimatorConfig(), strong_inliers=strong_inliers)
    est = PoseEstimator(
        conf, {cracker_model.name: cracker_library}, models={cracker_model.name: cracker_model}, renderer=get_renderer()
    )
    rec = est.estimate_image(img, Camera(K_SYN, 640, 480), [cracker_model.name])[0]
    assert rec.ok and rot_deg(rec.cam_from_model, T) < 2.0
    assert np.linalg.norm(rec.cam_from_model[:3, 3] - T[:3, 3]) < 0.01
    assert ("fine" in rec.timings) == (strong_inliers != 20)


@pytest.mark.parametrize("flips", [True, False])
def test_refinement_turns_a_flipped_pose_back(cracker_model, cracker_library, flips):
    """Start the refinement from the true pose turned 180 degrees about the box's vertical axis (the other
    face shows, same silhouette): with flips on it returns the true pose, without it cannot."""
    rng = np.random.default_rng(21)
    T = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T)
    xy_q, desc_q = detect(to_gray(img), EstimatorConfig().features)
    conf = dataclasses.replace(EstimatorConfig(), refine=RefineConfig(flips=flips))
    est = PoseEstimator(
        conf, {cracker_model.name: cracker_library}, models={cracker_model.name: cracker_model}, renderer=get_renderer()
    )
    F = max(cracker_model.flips(), key=lambda F: abs(np.linalg.eigh(F[:3, :3])[1][2, -1]))  # about model z
    start = PnpResult("ok", cam_from_model=T @ F, inliers=np.ones(6, bool))
    none = Correspondences(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, np.int32), (), 0)
    out = refine(est.objects, cracker_model.name, [(start, none, xy_q, desc_q)], Camera(K_SYN, 640, 480), xy_q, desc_q)
    if flips:
        assert out is not None and rot_deg(out.result.cam_from_model, T) < 2.0
        assert np.linalg.norm(out.result.cam_from_model[:3, 3] - T[:3, 3]) < 0.01
    else:
        assert out is None or rot_deg(out.result.cam_from_model, T) > 90


@pytest.mark.parametrize("name", sorted(p.stem for p in (Path(__file__).parent.parent / "pipelines").glob("*.yaml")))
def test_every_bundled_pipeline_loads(name):
    """Each preset in pipelines/ is a valid config; fast and paper turn the fine pass off, the default keeps it."""
    conf = load_estimator_config(load_yaml(Path(__file__).parent.parent / "pipelines" / f"{name}.yaml"), name)
    if name in ("fast", "paper"):
        assert not conf.fine.enabled
    if name == "gnc_pose":
        assert conf.fine.enabled and conf.refine.flips and conf.match.roi == "none"
        assert conf.track.enabled and conf.strong_inliers > 0
    assert conf.depth.enabled == (name == "rgbd") and conf.depth.search == (name == "rgbd")
    if name in ("paper", "oracle_roi", "tp_ub"):
        assert not conf.track.enabled or conf.match.roi == "gt_box" or conf.method == "tp_ub"


def test_implausible_poses_are_failed_not_reported(cracker_model, cracker_library):
    """A pose whose object would be a few pixels wide, fill the image many times over or sit behind the
    camera is reported as pnp_failed with the reason, never as an ok pose (it was 144 m away once)."""
    rng = np.random.default_rng(8)
    T = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T)
    cam = Camera(K_SYN, 640, 480)
    libs = {cracker_model.name: cracker_library}
    est = PoseEstimator(EstimatorConfig(), libs)
    assert est.objects.implausible(cracker_model.name, T, cam) == ""
    far, near, behind = T.copy(), T.copy(), T.copy()
    far[:3, 3] *= 200.0
    near[:3, 3] *= 0.02
    behind[:3, 3] *= -1.0
    assert "would span" in est.objects.implausible(cracker_model.name, far, cam)
    assert "would span" in est.objects.implausible(cracker_model.name, near, cam)
    assert "behind the camera" in est.objects.implausible(cracker_model.name, behind, cam)
    rec = est.estimate_image(img, cam, [cracker_model.name])[0]
    assert rec.ok and rot_deg(rec.cam_from_model, T) < 2.0
    strict = PoseEstimator(dataclasses.replace(EstimatorConfig(), min_object_px=5000.0), libs)
    rec = strict.estimate_image(img, cam, [cracker_model.name])[0]
    assert rec.status == "pnp_failed" and rec.reason.startswith("implausible pose: the object would span")
    assert rec.cam_from_model is None


@pytest.mark.parametrize("angle_bin_deg", [30.0, 0.0])
def test_locate_finds_the_object_centre_and_size(cracker_model, cracker_library, angle_bin_deg):
    from batchpose.method.correspondences import flann_index, locate
    from batchpose.method.features import detect_shapes

    conf = EstimatorConfig()
    index = flann_index(cracker_library.desc, conf.match)
    rng = np.random.default_rng(11)
    centre_m = cracker_library.pts3d.mean(axis=0)
    diam = float(np.linalg.norm(cracker_library.pts3d.max(axis=0) - cracker_library.pts3d.min(axis=0)))
    hits = 0
    for _ in range(5):
        T = random_pose(rng, cracker_model.center_m)
        xy, desc, shapes = detect_shapes(to_gray(compose(rng, cracker_model, T)), conf.features)
        located = locate(xy, shapes, desc, index, cracker_library, conf.match, 640, 480, angle_bin_deg=angle_bin_deg)
        assert len(located) == 1
        found = located[0]
        (cx, cy), size, votes = found.centre_xy, found.size_px, found.votes
        # The agreeing votes are 2D-3D pairs, most of them right.
        assert len(found.pairs) == votes
        X = found.pairs.X @ T[:3, :3].T + T[:3, 3]
        reproj = np.linalg.norm((X @ K_SYN.T)[:, :2] / X[:, 2:3] - found.pairs.x, axis=1)
        assert np.mean(reproj < 8.0) > 0.7, reproj
        c = T[:3, :3] @ centre_m + T[:3, 3]
        u, v = (K_SYN @ c)[:2] / c[2]
        d_px = K_SYN[0, 0] * diam / c[2]
        assert votes >= 4
        hits += np.hypot(cx - u, cy - v) < 0.2 * d_px and 0.7 < size / d_px < 1.4
    assert hits >= 4, hits
    # Too few frame keypoints: no location.
    assert locate(xy[:0], shapes[:0], desc[:0], index, cracker_library, conf.match, 640, 480) == []


def test_locate_config_is_checked():
    from batchpose.errors import ConfigError

    with pytest.raises(ConfigError, match="fine.locate_ratio must be in"):
        load_estimator_config({"fine": {"locate_ratio": 1.5}})
    with pytest.raises(ConfigError, match="fine.locate_peaks and fine.locate_votes must be >= 1"):
        load_estimator_config({"fine": {"locate_peaks": 0}})


def test_staged_view_matching_gives_the_pairs_of_all_views(cracker_model, cracker_library, monkeypatch):
    """match.first_views: the candidates of the first 8 voted views plus those of the other 24 select
    exactly the pairs that matching all 32 at once does; the estimator finds the pose either way and, on a
    sharp frame (strong after 8 views), never matches the other 24."""
    import batchpose.method.passes as passes_mod  # noqa: PLC0415
    from batchpose.method.correspondences import (  # noqa: PLC0415
        flann_index,
        match_template_to_query,
        template_to_query_candidates,
        top_k_pairs,
        vote_views,
    )

    rng = np.random.default_rng(8)
    T = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T)
    conf = EstimatorConfig()
    xy_q, desc_q = detect(to_gray(img), conf.features)
    lib, mc = cracker_library, conf.match
    views = vote_views(desc_q, flann_index(lib.desc, mc), lib, 32, mc)
    q_index = flann_index(desc_q, mc)
    a = template_to_query_candidates(q_index, lib, mc, None, views[:8])
    b = template_to_query_candidates(q_index, lib, mc, None, views[8:])
    staged = top_k_pairs(tuple(np.concatenate(p) for p in zip(a, b, strict=True)), lib, xy_q, mc)
    whole = match_template_to_query(xy_q, q_index, lib, mc, views=views)
    assert len(whole) > 20 and staged.templates == whole.templates
    np.testing.assert_array_equal(staged.x, whole.x)
    np.testing.assert_array_equal(staged.X, whole.X)

    tested: list[int] = []  # views per staged call the estimator makes

    def spy(query_index, lib_, conf_, mask=None, views_=None):
        tested.append(len(views_))
        return template_to_query_candidates(query_index, lib_, conf_, mask, views_)

    monkeypatch.setattr(passes_mod, "template_to_query_candidates", spy)
    for first in (8, 0):
        tested.clear()
        est = PoseEstimator(
            dataclasses.replace(conf, match=dataclasses.replace(mc, first_views=first)),
            {cracker_model.name: lib},
            models={cracker_model.name: cracker_model},
            renderer=get_renderer(),
        )
        rec = est.estimate_image(img, Camera(K_SYN, 640, 480), [cracker_model.name])[0]
        assert rec.ok and rot_deg(rec.cam_from_model, T) < 2.0
        assert tested == ([8] if first else [])


def test_warm_up_builds_every_library_index_before_the_first_frame(cracker_model, cracker_library):
    """A worker builds its FLANN library indices and renders each mesh once when it starts (warm_up), not
    inside its first frame."""
    renders = []

    class Spy:
        def render(self, key, *args, **kwargs):
            renders.append(key)
            return get_renderer().render(key, *args, **kwargs)

    libs = {cracker_model.name: cracker_library}
    est = PoseEstimator(EstimatorConfig(), libs, models={cracker_model.name: cracker_model}, renderer=Spy())
    built = est.objects._lib_index  # the estimator's library indices, filled as they are built
    assert built == {}
    est.warm_up()
    assert list(built) == [cracker_model.name] and built[cracker_model.name] is not None
    assert renders == [cracker_model.content_hash]


@pytest.mark.parametrize("joint_vote", [False, True])
def test_view_votes_and_locator_share_one_library_query(cracker_model, cracker_library, monkeypatch, joint_vote):
    """The view vote and the locator ask the library for the same nearest descriptors: given the one
    query's result they vote and locate exactly as when each queries itself (also under an ROI mask), and
    the estimator queries each keypoint set of an image once. With ``match.joint_vote`` the whole frame's
    keypoints are not queried at all: the presence check's joint query answers for them."""
    import batchpose.method.passes as passes_mod  # noqa: PLC0415
    import batchpose.method.shot as shot_mod  # noqa: PLC0415
    from batchpose.method.correspondences import flann_index, locate, nearest_with_rival, vote_views  # noqa: PLC0415
    from batchpose.method.features import detect_shapes  # noqa: PLC0415

    rng = np.random.default_rng(5)
    T = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T)
    conf = EstimatorConfig()
    lib, mc = cracker_library, conf.match
    index = flann_index(lib.desc, mc)
    xy, desc, shapes = detect_shapes(to_gray(img), conf.features)
    nearest = nearest_with_rival(desc, index, lib, mc)
    mask = xy[:, 0] < 320
    for m in (None, mask):
        np.testing.assert_array_equal(
            vote_views(desc, index, lib, 32, mc, m), vote_views(desc, index, lib, 32, mc, m, nearest)
        )
    own, shared = (locate(xy, shapes, desc, index, lib, mc, 640, 480, nearest=n) for n in (None, nearest))
    assert len(own) == len(shared) == 1 and own[0].centre_xy == shared[0].centre_xy and own[0].votes == shared[0].votes

    queried: list[int] = []

    def spy(desc_q, *a, **k):
        queried.append(id(desc_q))
        return nearest_with_rival(desc_q, *a, **k)

    located: list[int] = []

    def spy_locate(xy_q, shapes_q, desc_q, *a, **k):
        located.append(id(desc_q))
        return locate(xy_q, shapes_q, desc_q, *a, **k)

    monkeypatch.setattr(shot_mod, "nearest_with_rival", spy)
    monkeypatch.setattr(passes_mod, "locate", spy_locate)
    # Never strong, always weak: the fine pass and the locator run.
    weak = dataclasses.replace(
        conf,
        strong_inliers=0,
        fine=dataclasses.replace(conf.fine, locate_below=1.0),
        match=dataclasses.replace(conf.match, joint_vote=joint_vote),
    )
    est = PoseEstimator(
        weak, {cracker_model.name: lib}, models={cracker_model.name: cracker_model}, renderer=get_renderer()
    )
    rec = est.estimate_image(img, Camera(K_SYN, 640, 480), [cracker_model.name])[0]
    assert rec.ok and rot_deg(rec.cam_from_model, T) < 2.0
    assert len(queried) == len(set(queried)), queried
    assert located and len(set(located)) == 1, located  # the whole frame's keypoints
    # The locator reused the vote's query, or with the joint vote neither asked one (only the fine passes do).
    assert (located[0] in queried) != joint_vote, (located, queried)


def test_starts_that_project_alike_are_refined_once(cracker_model, cracker_library):
    """``refine.same_start_px``: of four starting poses, two the same, one 0.5 mm beside them (under a pixel
    in the image) and one 3 cm away, the two repeats are not refined again, and the refined pose is the one
    refining all four gives."""
    rng = np.random.default_rng(21)
    T = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T)
    xy_q, desc_q = detect(to_gray(img), EstimatorConfig().features)
    none = Correspondences(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, np.int32), (), 0)
    starts = [T, T.copy(), T.copy(), T.copy()]
    starts[2][0, 3] += 0.0005
    starts[3][0, 3] += 0.03
    passes = [(PnpResult("ok", cam_from_model=S, inliers=np.ones(6, bool)), none, xy_q, desc_q) for S in starts]
    out = {}
    for same_px in (0.0, 2.0):
        conf = dataclasses.replace(
            EstimatorConfig(), refine=RefineConfig(flips=False, iterations=1, same_start_px=same_px)
        )
        est = PoseEstimator(
            conf,
            {cracker_model.name: cracker_library},
            models={cracker_model.name: cracker_model},
            renderer=get_renderer(),
        )
        tried: list = []
        res = refine(est.objects, cracker_model.name, passes, Camera(K_SYN, 640, 480), xy_q, desc_q, tried=tried)
        assert res is not None
        out[same_px] = (len(tried), res.result.cam_from_model)
    assert out[0.0][0] == 4 and out[2.0][0] == 2
    assert rot_deg(out[0.0][1], out[2.0][1]) < 0.05
    assert np.linalg.norm(out[0.0][1][:3, 3] - out[2.0][1][:3, 3]) < 2e-4
    assert rot_deg(out[2.0][1], T) < 2.0


def test_no_fine_pass_in_a_box_as_large_as_the_image(cracker_model, cracker_library):
    """``fine.max_box_fraction`` 0.5: a box covering the frame is not searched again (it would be the
    whole-frame pass, upsampled); a box around the object is. By default (1) any box is."""
    from batchpose.method.passes import fine_pass  # noqa: PLC0415
    from batchpose.method.shot import Shot  # noqa: PLC0415

    rng = np.random.default_rng(5)
    T = random_pose(rng, cracker_model.center_m)
    gray = to_gray(compose(rng, cracker_model, T))
    shot = Shot(gray, Camera(K_SYN, 640, 480), "synthetic", {}, None)
    models = {cracker_model.name: cracker_model}
    unlimited = PoseEstimator(EstimatorConfig(), {cracker_model.name: cracker_library}, models=models)
    assert fine_pass(unlimited.objects, shot, cracker_model.name, (0, 0, 640, 480)) is not None  # default 1: no limit
    conf = dataclasses.replace(EstimatorConfig(), fine=FineConfig(max_box_fraction=0.5))
    est = PoseEstimator(conf, {cracker_model.name: cracker_library}, models=models)
    assert fine_pass(est.objects, shot, cracker_model.name, (0, 0, 640, 480)) is None
    assert fine_pass(est.objects, shot, cracker_model.name, (10, 10, 600, 400)) is None  # 77 % of the image
    around = fine_pass(est.objects, shot, cracker_model.name, (160, 80, 480, 400))  # 33 %
    assert around is not None and around.result is not None and len(around.pairs) > 20

"""The plane search (``plane.enabled``): the support plane, resting faces, and finding an object SIFT missed
where the found objects stand."""

from __future__ import annotations

import dataclasses
import re

import cv2
import numpy as np
import pytest
import trimesh

from batchpose.config import ConfigError, PlaneConfig, load_estimator_config
from batchpose.core.frames import Camera, Frame
from batchpose.core.poses import PoseRecord
from batchpose.io.mesh import load_mesh
from batchpose.method.estimator import PoseEstimator
from batchpose.method.on_plane import use_plane
from batchpose.method.render import get_renderer
from batchpose.method.sequence import Sequence
from batchpose.method.support import one_object_plane, resting_faces, stable_faces, support_plane
from batchpose.method.verify import verify_weak
from batchpose.method.views import look_at
from tests.conftest import GELATIN, K_SYN

#: A camera 0.55 m above a table (world z = 0), 0.45 m back, looking at the table's origin.
CAM_FROM_WORLD = look_at(np.array([0.0, -0.45, 0.55]), np.zeros(3), np.array([0.0, 0.0, 1.0]))


def _on_table(mesh, x: float, y: float, turn_deg: float, rest: int = 0) -> np.ndarray:
    """cam_from_model of the mesh resting on the table (its ``rest``-th stable pose) at (x, y), turned."""
    transforms, _ = mesh.compute_stable_poses(n_samples=1)
    a = np.deg2rad(turn_deg)
    world = np.eye(4)
    world[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
    world[:3, 3] = [x, y, 0.0]
    return CAM_FROM_WORLD @ world @ transforms[rest]


def _hull(model):
    return model.mesh.convex_hull


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_support_plane_of_objects_resting_on_a_table(cracker_model):
    gelatin = load_mesh(GELATIN)
    A = _on_table(cracker_model.mesh, -0.12, 0.05, 30)
    B = _on_table(gelatin.mesh, 0.1, -0.02, -50)
    plane = support_plane({"a": (A, _hull(cracker_model)), "b": (B, _hull(gelatin))}, PlaneConfig())
    table_normal = CAM_FROM_WORLD[:3, 2]  # world +z in the camera
    assert plane is not None and _angle_deg(plane.normal, table_normal) < 0.5
    assert plane.offset == pytest.approx(table_normal @ CAM_FROM_WORLD[:3, 3], abs=1e-3) and plane.spread_m < 1e-3
    lifted = B.copy()
    lifted[:3, 3] += 0.1 * table_normal  # held 10 cm above the table: no common plane
    assert support_plane({"a": (A, _hull(cracker_model)), "b": (lifted, _hull(gelatin))}, PlaneConfig()) is None
    assert support_plane({"a": (A, _hull(cracker_model))}, PlaneConfig()) is None  # one object
    # A third object on a 10 cm stand: the other two's table, unless every found object must rest on it.
    C = _on_table(gelatin.mesh, 0.05, 0.2, 10)
    C[:3, 3] += 0.1 * table_normal
    three = {"a": (A, _hull(cracker_model)), "b": (B, _hull(gelatin)), "c": (C, _hull(gelatin))}
    plane = support_plane(three, PlaneConfig())
    assert plane is not None and plane.objects == ("a", "b") and _angle_deg(plane.normal, table_normal) < 0.5
    assert support_plane(three, PlaneConfig(all_objects=True)) is None


def test_support_plane_is_one_the_objects_rest_on_with_a_face(cracker_model):
    """Two objects reach down equally to many planes; the one they rest on touches each with a stable face.
    A box balanced on its corner beside the cracker box (its lowest point on the table too) rests on nothing."""
    gelatin = load_mesh(GELATIN)
    A = _on_table(cracker_model.mesh, -0.12, 0.05, 30)
    tilt = np.eye(4)
    tilt[:3, :3] = cv2.Rodrigues(np.array([0.6, 0.5, 0.0]))[0]
    B = _on_table(gelatin.mesh, 0.1, -0.02, 0) @ tilt
    low = gelatin.mesh.convex_hull.vertices @ (CAM_FROM_WORLD.T @ B)[:3, :3].T  # world frame, about the origin
    B[:3, 3] -= CAM_FROM_WORLD[:3, 2] * (low[:, 2].min() + (np.linalg.inv(CAM_FROM_WORLD) @ B)[2, 3])
    found = {"a": (A, _hull(cracker_model)), "b": (B, _hull(gelatin))}
    stable = {"a": stable_faces(cracker_model.mesh)[0], "b": stable_faces(gelatin.mesh)[0]}
    table = support_plane(found, PlaneConfig())
    assert table is not None and _angle_deg(table.normal, CAM_FROM_WORLD[:3, 2]) < 0.5  # both reach it
    assert support_plane(found, PlaneConfig(), stable) is None
    B_flat = _on_table(gelatin.mesh, 0.1, -0.02, 0)
    flat = support_plane({"a": found["a"], "b": (B_flat, _hull(gelatin))}, PlaneConfig(), stable)
    assert flat is not None and _angle_deg(flat.normal, CAM_FROM_WORLD[:3, 2]) < 0.5


def test_one_object_rests_on_its_face_nearest_the_image_up(cracker_model):
    """One found object: the surface is its resting face nearest the image's up direction, when that is clear
    (a camera looking 30 degrees down, rolled a little or not); looking 60 degrees down, a side face is nearly
    as near, and straight down the image's up says nothing: no plane."""
    faces = resting_faces(stable_faces(cracker_model.mesh), PlaneConfig().min_stable)
    hull = _hull(cracker_model)

    def seen_from(eye: np.ndarray, up=(0.0, 0.0, -1.0)) -> tuple[np.ndarray, np.ndarray]:
        """(cam_from_world, cam_from_model) of a camera at ``eye``; look_at's ``up`` is the image's down."""
        cam_from_world = look_at(eye, np.zeros(3), np.asarray(up))
        return cam_from_world, cam_from_world @ np.linalg.inv(CAM_FROM_WORLD) @ _on_table(cracker_model.mesh, 0, 0, 20)

    cam, T = seen_from(np.array([0.0, -0.9, 0.52]))  # 30 degrees down
    plane = one_object_plane("a", T, hull, faces, PlaneConfig())
    assert plane is not None and _angle_deg(plane.normal, cam[:3, 2]) < 0.5 and plane.objects == ("a",)
    assert plane.offset == pytest.approx(cam[:3, 2] @ cam[:3, 3], abs=1e-3)
    assert one_object_plane("a", T, hull, faces, PlaneConfig(one_object_tilt_deg=0)) is None  # off
    assert one_object_plane("a", T, hull, faces, PlaneConfig(one_object_tilt_deg=25)) is None  # beyond the tilt
    assert one_object_plane("a", *seen_from(np.array([0.0, -0.3, 0.52]))[1:], hull, faces, PlaneConfig()) is None
    assert (
        one_object_plane("a", *seen_from(np.array([0.0, 0.0, 0.6]), (0, -1, 0))[1:], hull, faces, PlaneConfig()) is None
    )
    rolled = np.eye(4)
    rolled[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.0, np.deg2rad(15.0)]))[0]  # a hand-held camera's roll
    plane = one_object_plane("a", rolled @ T, hull, faces, PlaneConfig())
    assert plane is not None and _angle_deg(plane.normal, rolled[:3, :3] @ cam[:3, 2]) < 0.5


def test_resting_faces_of_a_box():
    faces = resting_faces(stable_faces(trimesh.creation.box(extents=(0.1, 0.2, 0.3))), 0.02)
    assert len(faces) == 6 and all(np.isclose(np.abs(f).max(), 1.0) for f in faces)
    # The likeliest first: the box lies on one of its two largest faces (normal along x).
    assert np.isclose(abs(faces[0][0]), 1.0)


def test_plane_config_is_checked():
    with pytest.raises(ConfigError, match=r"plane.min_objects must be >= 2, got 1"):
        load_estimator_config({"plane": {"min_objects": 1}})
    with pytest.raises(ConfigError, match=r"plane.min_edge must be in \[0, 1\], got 1.5"):
        load_estimator_config({"plane": {"min_edge": 1.5}})
    with pytest.raises(ConfigError, match=r"plane.edge_confirms must be in \[0, 1\], got -0.1"):
        load_estimator_config({"plane": {"edge_confirms": -0.1}})
    with pytest.raises(ConfigError, match=r"verify_below must be in \[0, 1\], got 1.5"):
        load_estimator_config({"verify_below": 1.5})
    with pytest.raises(ConfigError, match=r"unknown key.*plane"):
        load_estimator_config({"plane": {"enabled": True, "min_object": 2}})


def _scene(cracker_model, with_cracker: bool, seed: int = 3):
    """Two gelatin boxes on a grey table, and (if ``with_cracker``) the cracker box lying between them."""
    r = get_renderer()
    gelatin = load_mesh(GELATIN)
    poses = {
        "gelatin_a": _on_table(gelatin.mesh, -0.16, 0.08, 20),
        "gelatin_b": _on_table(gelatin.mesh, 0.15, 0.1, -35),
    }
    T = _on_table(cracker_model.mesh, 0.0, -0.02, 70)
    meshes = {"gelatin_a": gelatin, "gelatin_b": gelatin}
    if with_cracker:
        meshes[cracker_model.name], poses[cracker_model.name] = cracker_model, T
    rng = np.random.default_rng(seed)
    img = np.full((480, 640, 3), 150, np.uint8)
    img[:] = (np.clip(rng.normal(150, 4, img.shape), 0, 255)).astype(np.uint8)
    zbuf = np.full((480, 640), np.inf)
    for name, P in poses.items():
        m = meshes[name]
        rgb, depth = r.render(m.content_hash, m.mesh, P, K_SYN, 640, 480, "lit")
        on = (depth > 0) & (depth < zbuf)
        img[on], zbuf[on] = rgb[on], depth[on]
    frame = Frame("table", 0, 0, 0, Camera(K_SYN, 640, 480), "png", cv2.imencode(".png", img[:, :, ::-1])[1].tobytes())
    models = {"gelatin_a": gelatin, "gelatin_b": gelatin, cracker_model.name: cracker_model}
    found = [PoseRecord("table", n, "ok", cam_from_model=poses[n], confidence=0.9) for n in ("gelatin_a", "gelatin_b")]
    return frame, img, models, found, T


def _plane_search(cracker_model, cracker_library, with_cracker: bool, frames: int = 1, **conf):
    frame, img, models, found, T = _scene(cracker_model, with_cracker)
    conf = load_estimator_config({"track": {"enabled": False}} | conf)
    est = PoseEstimator(conf, {cracker_model.name: cracker_library}, models=models, renderer=get_renderer())
    recs, seq = [], Sequence()
    for im_id in range(frames):  # a 30 Hz sequence of the same image
        frame = dataclasses.replace(frame, im_id=im_id, stamp_ns=im_id * 33_000_000)
        recs.append(PoseRecord("table", cracker_model.name, "too_few_matches"))
        use_plane(est.objects, frame, img, [*found, recs[-1]], seq)
    return (recs[0] if frames == 1 else recs), T


def test_plane_search_finds_an_object_lying_among_found_ones(cracker_model, cracker_library):
    from tests.test_depth import _adds_mm

    rec, T = _plane_search(cracker_model, cracker_library, with_cracker=True)
    assert rec.ok and rec.reason.startswith(
        "found by the plane search (no SIFT pose): resting on the surface under gelatin_a, gelatin_b"
    )
    assert 0.3 < rec.confidence <= 0.5 and rec.timings["plane"] > 0
    assert _adds_mm(cracker_model, rec.cam_from_model, T) < 10


def test_plane_search_keeps_nothing_where_the_object_is_not(cracker_model, cracker_library):
    rec, _ = _plane_search(cracker_model, cracker_library, with_cracker=False)
    assert rec.status == "too_few_matches" and rec.cam_from_model is None


def test_plane_search_follows_its_placement_into_the_next_frame(cracker_model, cracker_library):
    from tests.test_depth import _adds_mm

    recs, T = _plane_search(cracker_model, cracker_library, True, frames=2, track={"enabled": True})
    assert [r.reason.split(" (")[0] for r in recs] == [
        "found by the plane search",
        "followed from the previous frame's plane search",
    ]
    assert _adds_mm(cracker_model, recs[1].cam_from_model, T) < 10
    assert recs[1].timings["plane"] < recs[0].timings["plane"]


@pytest.mark.parametrize("off_m, replaced", [(0.2, True), (0.0, False)])
def test_a_weak_sift_pose_is_replaced_only_by_a_placement_that_fits_better(
    cracker_model, cracker_library, off_m, replaced
):
    """A SIFT pose under plane.min_confidence is searched past: a wrong one (20 cm off) gives way to the
    placement, the right one (which the frame matches better than any placement) stays."""
    frame, img, models, found, T = _scene(cracker_model, True)
    weak = T.copy()
    weak[:3, 3] += [off_m, 0.0, 0.0]
    est = PoseEstimator(
        load_estimator_config({"track": {"enabled": False}}),
        {cracker_model.name: cracker_library},
        models=models,
        renderer=get_renderer(),
    )
    rec = PoseRecord("table", cracker_model.name, "ok", cam_from_model=weak, confidence=0.35)
    use_plane(est.objects, frame, img, [*found, rec], Sequence())
    assert rec.ok and rec.reason.startswith("found by the plane search (a weak SIFT pose)") == replaced
    assert (rec.cam_from_model is weak) != replaced and rec.timings["plane"] > 0


def test_a_placement_is_scored_by_how_closely_the_frames_edges_follow_its_outline(cracker_model):
    """``Placed.edge``: at the right place the frame's edges run along the silhouette's outline, a centimetre
    aside far fewer do; a frame blurred to no edges at all says nothing (NaN: ``plane.min_edge`` is not
    checked there)."""
    from batchpose.method.plane import Target, _edge_credit, _Judge

    _, img, _, _, T = _scene(cracker_model, with_cracker=True)
    r = get_renderer()
    m = cracker_model
    target = Target(np.asarray(m.mesh.convex_hull.vertices), np.asarray(m.mesh.bounding_box.centroid),
                    m.diameter_m, (), np.zeros(1))  # fmt: skip
    none_found = np.zeros((480, 640), bool)

    def edge(image: np.ndarray, P: np.ndarray) -> float:
        judge = _Judge(image, np.zeros((480, 640), np.float32), none_found, np.full((480, 640), np.inf),
                       lambda P, K, w, h: r.render(m.content_hash, m.mesh, P, K, w, h, "lit"), K_SYN, target, 384,
                       PlaneConfig(), CAM_FROM_WORLD[:3, 2], _edge_credit(image, none_found))  # fmt: skip
        return judge(P)[1].edge

    aside = T.copy()
    aside[:3, 3] += 0.01 * CAM_FROM_WORLD[:3, 0]  # 1 cm along the table
    assert edge(img, T) > 0.85
    assert edge(img, aside) < edge(img, T) - 0.3
    assert np.isnan(edge(cv2.GaussianBlur(img, (0, 0), 4), T))


def test_plane_search_keeps_no_placement_its_edges_do_not_follow(cracker_model, cracker_library):
    rec, _ = _plane_search(cracker_model, cracker_library, True, plane={"min_edge": 0.99})
    assert rec.status == "too_few_matches" and rec.cam_from_model is None


@pytest.mark.parametrize(
    "checks, found",
    [
        ({"min_colour": 10.0}, True),  # colour fails, the contrast and the edges pass
        ({"min_contrast": 10.0}, True),  # contrast fails
        ({"min_colour": 10.0, "min_contrast": 10.0}, False),  # edges stand in for one colour cue, not both
        ({"min_colour": 10.0, "edge_confirms": 0.99}, False),  # the edges are not close enough for that
    ],
)
def test_edges_stand_in_for_one_failed_colour_check(cracker_model, cracker_library, checks, found):
    """``plane.edge_confirms``: a placement whose outline the frame's edges follow closely is kept although its
    colours fail one of the two colour checks (a pale bottle on a white table); without it, it is not."""
    from tests.test_depth import _adds_mm

    rec, T = _plane_search(cracker_model, cracker_library, True, plane={"edge_confirms": 0.75} | checks)
    assert rec.ok == found
    if found:
        assert _adds_mm(cracker_model, rec.cam_from_model, T) < 10
        off, _ = _plane_search(cracker_model, cracker_library, True, plane=checks | {"edge_confirms": 0.0})
        assert not off.ok


def test_a_failing_plane_search_leaves_the_frame_its_poses(cracker_model, cracker_library, monkeypatch, caplog):
    """An unexpected error in the optional stage is a warning; the records stay as the estimate made them."""
    import batchpose.method.on_plane

    def boom(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(batchpose.method.on_plane, "support_plane", boom)
    frame, *_ = _scene(cracker_model, True)
    recs = []
    for enabled in (True, False):
        conf = load_estimator_config(
            # (without the presence check, which would make the object absent and skip the plane search)
            {"features": {"n_features": 4}, "track": {"enabled": False}, "plane": {"enabled": enabled},
             "match": {"presence_votes": 0}}
        )  # fmt: skip
        est = PoseEstimator(conf, {cracker_model.name: cracker_library}, models={cracker_model.name: cracker_model},
                            renderer=get_renderer())  # fmt: skip
        recs += est.estimate_frame(frame, [cracker_model.name])
    assert "table: use_plane failed (RuntimeError: boom); poses as estimated before it" in caplog.text
    assert recs[0].status == recs[1].status and recs[0].reason == recs[1].reason
    np.testing.assert_array_equal(recs[0].cam_from_model, recs[1].cam_from_model)


@pytest.mark.parametrize("off_m, kept", [(0.0, True), (0.25, False)])
def test_a_weak_pose_must_look_like_the_frame(cracker_model, cracker_library, off_m, kept):
    """verify_below: a weak pose (confidence < 0.5) whose rendered mesh does not correlate with the frame (here
    25 cm off, on the table) becomes low_confidence; the right one stays."""
    frame, img, models, found, T = _scene(cracker_model, True)
    pose = T.copy()
    pose[:3, 3] += [off_m, 0.0, 0.0]
    est = PoseEstimator(load_estimator_config({}), {cracker_model.name: cracker_library}, models=models,
                        renderer=get_renderer())  # fmt: skip
    rec = PoseRecord("table", cracker_model.name, "ok", cam_from_model=pose, confidence=0.35)
    verify_weak(est.objects, frame, img, [*found, rec], {})
    assert rec.ok == kept
    if not kept:
        assert rec.status == "low_confidence" and rec.reason.startswith(
            "weak pose (confidence 0.35 < verify_below 0.5) whose mesh does not look like the frame there"
        )


@pytest.mark.parametrize("replaced_off_m", [0.0, 0.3])
def test_a_retry_pose_the_texture_check_rejects_gives_back_the_pose_it_replaced(
    cracker_model, cracker_library, replaced_off_m
):
    """A retry's more confident pose that does not look like the frame is not reported; the weak pose it replaced
    is checked in turn and reported when it passes (both were lost before), not when it fails too."""
    frame, img, models, found, T = _scene(cracker_model, True)
    wrong, replaced = T.copy(), T.copy()
    wrong[:3, 3] += [0.25, 0.0, 0.0]
    replaced[:3, 3] += [-replaced_off_m, 0.0, 0.0]
    est = PoseEstimator(load_estimator_config({}), {cracker_model.name: cracker_library}, models=models,
                        renderer=get_renderer())  # fmt: skip
    first = PoseRecord("table", cracker_model.name, "ok", cam_from_model=replaced, confidence=0.35)
    retry = PoseRecord("table", cracker_model.name, "ok", "found with keypoints at contrast 0.01",
                       cam_from_model=wrong, confidence=0.45, timings={"match": 1.0})  # fmt: skip
    replaced = {id(retry): (retry, first)}  # as the retry records a replacement
    records = [*found, retry]
    verify_weak(est.objects, frame, img, records, replaced)
    rejected = "weak pose (confidence 0.45 < verify_below 0.5) whose mesh does not look like the frame there"
    if replaced_off_m == 0.0:
        assert records[-1] is first and first.ok and first.timings["match"] == 1.0
        assert first.reason.startswith(f"kept over a retry's more confident pose: {rejected}"), first.reason
    else:
        assert records[-1] is retry and retry.status == "low_confidence" and retry.reason.startswith(rejected)


@pytest.mark.parametrize("where", ["far", "off"])
def test_a_weak_pose_the_frame_barely_shows_is_not_kept(cracker_model, cracker_library, where):
    """verify_below: a weak pose that puts the object where its mesh covers (almost) no pixel of the frame —
    25 m away, past the renderer's far plane (a 7-inlier pose 23 m off was reported ok in a tabletop frame), or
    beside the image — cannot be checked, so it is not reported ok; a confident one is not judged."""
    frame, img, models, found, T = _scene(cracker_model, True)
    pose = T.copy()
    if where == "far":
        pose[:3, 3] *= 25.0 / np.linalg.norm(T[:3, 3])
    else:
        pose[:3, 3] += [2.0, 0.0, 0.0]
    est = PoseEstimator(load_estimator_config({}), {cracker_model.name: cracker_library}, models=models,
                        renderer=get_renderer())  # fmt: skip
    weak = PoseRecord("table", cracker_model.name, "ok", cam_from_model=pose, confidence=0.35)
    sure = PoseRecord("table", cracker_model.name, "ok", cam_from_model=pose, confidence=0.6)
    for rec in (weak, sure):
        verify_weak(est.objects, frame, img, [*found, rec], {})
    assert sure.ok and weak.status == "low_confidence"
    assert re.fullmatch(
        r"weak pose \(confidence 0\.35 < verify_below 0\.5\) that shows \d+ px of the mesh in the frame "
        r"\(object centre \d+\.\d m away\): too little to check it against",
        weak.reason,
    ), weak.reason


def _marker_on_table(x: float, y: float, turn_deg: float):
    """A thin box (a marker) lying on the table at (x, y), turned: the plane search's target and plane, its
    pose, its pixels' (N, 2) hull corners, and a colour log-odds map with the table at -0.5 and it at 2."""
    from batchpose.method.plane import Target

    marker = trimesh.creation.box(extents=(0.12, 0.015, 0.015))
    hull = np.asarray(marker.convex_hull.vertices)
    target = Target(hull, np.zeros(3), 0.121, tuple(resting_faces(stable_faces(marker), 0.02)), np.zeros(1))
    T = _on_table(marker, x, y, turn_deg)
    p = (hull @ T[:3, :3].T + T[:3, 3]) @ K_SYN.T
    px = p[:, :2] / p[:, 2:]
    odds = np.full((480, 640), -0.5, np.float32)
    cv2.fillConvexPoly(odds, cv2.convexHull(np.round(px).astype(np.int32)), 2.0)
    return target, _table_plane(), T, px, odds


def _table_plane():
    """The table (world z = 0) as the plane search's support plane."""
    from batchpose.method.support import Plane

    normal = CAM_FROM_WORLD[:3, 2]
    return Plane(normal, float(normal @ CAM_FROM_WORLD[:3, 3]), 0.0, ("a", "b"))


def test_the_coarse_search_keeps_a_thin_object_standing_out_beside_a_broad_patch_of_its_colours():
    """A broad patch of the object's colours nearer the camera (a shadow, a cloth) holds more of them than the
    thin object itself does: the coarse search must still offer a placement where the object stands out."""
    from batchpose.method.plane import _places

    target, plane, T, _, odds = _marker_on_table(0.1, 0.1, 30)  # ~115 x 15 px, rows 292-357
    odds[370:, 60:580] = 2.0  # the patch
    found = _places(odds, K_SYN, plane, target, 16, PlaneConfig())
    near = [np.linalg.norm(F[:3, 3] - T[:3, 3]) for F in found]
    assert min(near) < 0.2 * target.diameter_m, sorted(near)[:4]  # by colours held alone: 9 cm off at best
    assert sum(d > target.diameter_m for d in near) >= 8  # the patch keeps its candidates too


def test_the_coarse_search_reaches_an_object_near_the_frames_border():
    """A marker lying crosswise 20 px above the frame's bottom edge (rows 442-461): a square kernel as wide as
    the marker is long reaches past the frame there, yet the search must offer a placement at the marker."""
    from batchpose.method.plane import _places

    target, plane, T, px, odds = _marker_on_table(0.0, 0.3, 0)
    assert 440 <= px[:, 1].min() and px[:, 1].max() < 470
    found = _places(odds, K_SYN, plane, target, 16, PlaneConfig())
    near = [np.linalg.norm(F[:3, 3] - T[:3, 3]) for F in found]
    assert min(near) < 0.1 * target.diameter_m, sorted(near)[:4]  # kernels kept inside the frame: 8 cm off


@pytest.mark.parametrize("rest", [0, 1, 2])
def test_refacing_offers_the_object_on_its_other_faces_at_the_same_place(cracker_model, rest):
    """A box placed on the wrong face (its silhouette barely differs): among its refaced poses is the box on
    the face it lies on, turned as it lies (long axis along the placement's, one way or the other), resting on
    the plane where the placement was in the image (its centre on the same viewing ray)."""
    from batchpose.method.plane import Target, _refaced, _turn_deg

    mesh = cracker_model.mesh
    hull = np.asarray(mesh.convex_hull.vertices)
    centre = np.asarray(mesh.bounding_box.centroid)
    faces = tuple(resting_faces(stable_faces(mesh), 0.02))
    target = Target(hull, centre, cracker_model.diameter_m, faces, np.zeros(1))
    plane = _table_plane()
    truth = _on_table(mesh, 0.05, 0.02, 40, rest=rest)
    wrong = _on_table(mesh, 0.05, 0.02, 40, rest=(rest + 1) % 3)
    offered = _refaced(wrong, plane, target)
    assert len(offered) >= 2 * len(faces)
    best = min(offered, key=lambda T: _turn_deg(T, truth))
    assert _turn_deg(best, truth) < 3.0
    for T in offered:
        assert abs((hull @ T[:3, :3].T + T[:3, 3]).dot(plane.normal).min() - plane.offset) < 1e-6  # resting on it
        c, w = T[:3, :3] @ centre + T[:3, 3], wrong[:3, :3] @ centre + wrong[:3, 3]
        assert np.allclose(c / c[2], w / w[2])  # where the placement was in the image

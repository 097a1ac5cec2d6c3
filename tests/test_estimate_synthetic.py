"""Synthetic round trip: render the bundled cracker box at seeded random poses over textured
backgrounds, estimate with the full pipeline, check ADD against 0.1 x diameter (issue 2)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from batchpose.config import EstimatorConfig
from batchpose.core.frames import Camera
from batchpose.method.estimator import PoseEstimator
from batchpose.method.render import get_renderer
from batchpose.method.views import look_at
from tests.conftest import K_SYN


def random_pose(rng: np.random.Generator, center: np.ndarray) -> np.ndarray:
    """cam_from_model: 0.5-1.0 m away, any azimuth, elevation 0-60 deg, in-plane roll +-30 deg,
    object centre shifted up to 60 px off the optical axis."""
    az = rng.uniform(-np.pi, np.pi)
    el = np.deg2rad(rng.uniform(0.0, 60.0))
    dist = rng.uniform(0.5, 1.0)
    eye = center + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T = look_at(eye, center, np.array([0.0, 0.0, 1.0]))
    roll = np.deg2rad(rng.uniform(-30, 30))
    Rz = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
    T[:3, :3] = Rz @ T[:3, :3]
    T[:3, 3] = Rz @ T[:3, 3]
    shift = rng.uniform(-60, 60, size=2) * dist / K_SYN[0, 0]
    T[:2, 3] += shift
    return T


def textured_background(rng: np.random.Generator, w: int = 640, h: int = 480) -> np.ndarray:
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), (0, 0), 3)
    for _ in range(40):
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        p = rng.integers(0, [w, h])
        if rng.random() < 0.5:
            cv2.rectangle(img, tuple(int(v) for v in p), tuple(int(v) for v in p + rng.integers(10, 120, 2)), color, -1)
        else:
            cv2.circle(img, tuple(int(v) for v in p), int(rng.integers(5, 60)), color, -1)
    return img


def compose(rng, model, T) -> np.ndarray:
    rgb, depth = get_renderer().render(model.content_hash, model.mesh, T, K_SYN, 640, 480, shading="lit")
    img = textured_background(rng)
    mask = depth > 0
    img[mask] = rgb[mask]
    noisy = img.astype(np.float32) + rng.normal(0, 3.0, img.shape)
    return np.clip(noisy, 0, 255).astype(np.uint8)


def estimator_with(model, library, **features) -> PoseEstimator:
    """The default estimator of one object, with these ``features`` settings and without the presence check
    (these frames show the object, as the ground truth says under ``targets: annotations``: a dim object
    without evidence at the base contrast would be ``absent``, not retried)."""
    import dataclasses

    conf = EstimatorConfig()
    conf = dataclasses.replace(conf, features=dataclasses.replace(conf.features, **features))
    conf = dataclasses.replace(conf, match=dataclasses.replace(conf.match, presence_votes=0))
    return PoseEstimator(conf, {model.name: library}, models={model.name: model}, renderer=get_renderer())


def dim_frame(rng, model, T, contrast: float, blur_px: float = 0.0) -> np.ndarray:
    """The object lit at pose ``T`` over a textured background, its colours pulled towards their mean to
    ``contrast`` of their spread, optionally blurred, with sensor noise."""
    rgb, depth = get_renderer().render(model.content_hash, model.mesh, T, K_SYN, 640, 480, "lit")
    img = textured_background(rng).astype(np.float32)
    obj = rgb.astype(np.float32)
    mean = obj[depth > 0].mean(axis=0)
    img[depth > 0] = (mean + contrast * (obj - mean))[depth > 0]
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    return np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)


def add_error(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    a = pts @ T_est[:3, :3].T + T_est[:3, 3]
    b = pts @ T_gt[:3, :3].T + T_gt[:3, 3]
    return float(np.linalg.norm(a - b, axis=1).mean())


@pytest.mark.slow
def test_round_trip_30_poses(cracker_model, cracker_library):
    rng = np.random.default_rng(2026)
    est = PoseEstimator(
        EstimatorConfig(),
        {cracker_model.name: cracker_library},
        models={cracker_model.name: cracker_model},
        renderer=get_renderer(),
    )
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    cam = Camera(K_SYN, 640, 480)
    errors = []
    for _ in range(30):
        T = random_pose(rng, cracker_model.center_m)
        rec = est.estimate_image(compose(rng, cracker_model, T), cam, [cracker_model.name])[0]
        errors.append(add_error(rec.cam_from_model, T, pts) if rec.ok else np.inf)
    errors = np.array(errors)
    rate = float(np.mean(errors < 0.1 * cracker_model.diameter_m))
    print(f"ADD<0.1d rate {rate:.2f}; median ADD {np.median(errors) * 1000:.1f} mm")
    assert rate >= 0.9, f"ADD < 0.1 d on {rate:.0%} of 30 poses; errors (mm): {np.round(errors * 1000, 1)}"


def test_a_dim_object_is_found_by_the_retry_at_a_lower_contrast(cracker_model, cracker_library):
    """The box at a tenth of its contrast: the default keypoints find it in at most one of six frames; the
    retry at ``features.retry_contrast_threshold`` 0.01 finds at least four more, within 0.05 d; a confident
    pose the first estimate found stays exactly as it was, a weak one is replaced only by a stronger one.
    An object in ``no_retry`` gets the first estimate only."""
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    cam = Camera(K_SYN, 640, 480)
    plain = estimator_with(cracker_model, cracker_library, retry_contrast_threshold=0.0)
    retried = estimator_with(cracker_model, cracker_library, retry_contrast_threshold=0.01)
    rng = np.random.default_rng(7)
    found = {"plain": 0, "retry": 0}
    for _ in range(6):
        T = random_pose(rng, cracker_model.center_m)
        img = dim_frame(rng, cracker_model, T, 0.1)
        a = plain.estimate_image(img, cam, [cracker_model.name])[0]
        b = retried.estimate_image(img, cam, [cracker_model.name])[0]
        c = retried.estimate_image(img, cam, [cracker_model.name], no_retry=frozenset([cracker_model.name]))[0]
        assert (c.status, c.reason) == (a.status, a.reason)  # no_retry: the first estimate only
        if a.ok:
            np.testing.assert_array_equal(a.cam_from_model, c.cam_from_model)
            found["plain"] += add_error(a.cam_from_model, T, pts) < 0.05 * cracker_model.diameter_m
            if a.confidence >= retried.conf.verify_below:
                np.testing.assert_array_equal(a.cam_from_model, b.cam_from_model)
            else:  # a weak pose is replaced only by a more confident one
                assert b.ok and b.confidence >= a.confidence
        else:
            assert b.ok == ("contrast 0.01" in b.reason)
            found["retry"] += b.ok and add_error(b.cam_from_model, T, pts) < 0.05 * cracker_model.diameter_m
    print(found)
    assert found["plain"] <= 1 and found["retry"] >= 4, found


def test_a_second_retry_at_a_finer_sigma_only_touches_what_the_first_left_weak(cracker_model, cracker_library):
    """``features.retry_sigma``: small, blurred, dim boxes (1.4-2.8 m, a fifth of their contrast). Where the
    retry at the lower contrast gives a confident pose, the second retry leaves it exactly as it was; where
    it leaves the object missing or weak, the second retry's pose is kept only when it is ok and more
    confident, and then says so. In these frames it does replace at least one pose."""
    cam = Camera(K_SYN, 640, 480)
    once = estimator_with(cracker_model, cracker_library, retry_sigma=0.0)
    twice = estimator_with(cracker_model, cracker_library, retry_sigma=1.2)
    rng = np.random.default_rng(11)
    replaced = 0
    for _ in range(8):
        T = random_pose(rng, cracker_model.center_m)
        T[:3, 3] *= 2.8
        img = dim_frame(rng, cracker_model, T, 0.2, blur_px=1.0)
        a = once.estimate_image(img, cam, [cracker_model.name])[0]
        b = twice.estimate_image(img, cam, [cracker_model.name])[0]
        if a.ok and a.confidence >= once.conf.verify_below:
            np.testing.assert_array_equal(a.cam_from_model, b.cam_from_model)
        elif "sigma 1.2" in b.reason:
            assert b.ok and (not a.ok or b.confidence > a.confidence)
            replaced += 1
        else:
            assert (b.status, b.reason) == (a.status, a.reason)
    assert replaced >= 1


def default_then(model, library, changes) -> tuple:
    """One seeded frame of ``model`` estimated with the default config, then with the fields ``changes(first
    record)`` returns changed (and no retry): the two records."""
    import dataclasses

    rng = np.random.default_rng(7)
    T = random_pose(rng, model.center_m)
    img, cam = compose(rng, model, T), Camera(K_SYN, 640, 480)
    models, libraries = {model.name: model}, {model.name: library}
    rec = PoseEstimator(EstimatorConfig(), libraries, models=models, renderer=get_renderer()).estimate_image(
        img, cam, [model.name]
    )[0]
    changed = dataclasses.replace(EstimatorConfig(), **changes(rec))
    conf = dataclasses.replace(changed, features=dataclasses.replace(changed.features, retry_contrast_threshold=0))
    other = PoseEstimator(conf, libraries, models=models, renderer=get_renderer()).estimate_image(
        img, cam, [model.name]
    )[0]
    return rec, other


def test_a_pose_needs_inliers_on_distinct_pixels(cracker_model, cracker_library):
    """``min_distinct_inliers``: the inliers are counted by the frame pixels they lie on; a pose on fewer than
    the floor is pnp_failed, with a reason naming the count (here the floor is raised over this pose's)."""

    def distinct(rec) -> int:
        return len(np.unique(np.round(rec.inliers_px).astype(np.int64), axis=0))

    rec, failed = default_then(cracker_model, cracker_library, lambda r: {"min_distinct_inliers": distinct(r) + 1})
    assert rec.ok
    assert 4 <= distinct(rec) <= rec.n_inliers
    assert failed.status == "pnp_failed"
    assert "distinct pixels, need" in failed.reason

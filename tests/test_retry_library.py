"""``render.retry_shading``: a second template library that the objects a full estimate misses, or finds
only weakly, are matched against once more (:func:`batchpose.method.single.retry_library`); and
``retry_rejected``: the retries for an object whose pose the verification score rejects."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from batchpose.config import EstimatorConfig
from batchpose.core.frames import Camera
from batchpose.method.estimator import PoseEstimator
from batchpose.method.render import get_renderer
from batchpose.method.single import has_retries
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import add_error, compose, random_pose


def scrambled(library):
    """The library with its descriptors dealt to the wrong keypoints: it matches, but to nowhere consistent
    (and has no cached index: ``folder`` is None)."""
    perm = np.random.default_rng(0).permutation(len(library.desc))
    return dataclasses.replace(library, desc=library.desc[perm], folder=None)


def estimator(model, first, second=None, **changes) -> PoseEstimator:
    """Flat templates first, ``second`` as the lit retry library; no other retry, no presence check;
    ``changes`` to the rest of the config."""
    conf = EstimatorConfig()
    conf = dataclasses.replace(
        conf,
        render=dataclasses.replace(conf.render, shading="flat", retry_shading="lit"),
        features=dataclasses.replace(conf.features, retry_contrast_threshold=0.0),
        match=dataclasses.replace(conf.match, presence_votes=0),
        **changes,
    )
    second = None if second is None else {model.name: second}
    return PoseEstimator(conf, {model.name: first}, models={model.name: model}, renderer=get_renderer(),
                         retry_libraries=second)  # fmt: skip


def test_the_second_library_finds_what_the_first_misses_and_leaves_confident_poses(cracker_model, cracker_library):
    """With a first library that cannot match the box, the second one finds it, within 0.1 d, and the
    record says so; with a good first library, a confident pose is exactly what it is without a second
    library (the second, here useless, one is not asked)."""
    name, cam = cracker_model.name, Camera(K_SYN, 640, 480)
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    bad = scrambled(cracker_library)
    missing = estimator(cracker_model, bad)
    rescued = estimator(cracker_model, bad, cracker_library)
    alone = estimator(cracker_model, cracker_library)
    spoilt = estimator(cracker_model, cracker_library, bad)
    rng = np.random.default_rng(5)
    for _ in range(2):
        T = random_pose(rng, cracker_model.center_m)
        img = compose(rng, cracker_model, T)
        a = missing.estimate_image(img, cam, [name])[0]
        assert not a.ok or a.confidence < missing.conf.verify_below, (a.status, a.reason)
        b = rescued.estimate_image(img, cam, [name])[0]
        assert b.ok and b.reason == "found with the lit templates", (b.status, b.reason)
        assert add_error(b.cam_from_model, T, pts) < 0.1 * cracker_model.diameter_m
        c, d = alone.estimate_image(img, cam, [name])[0], spoilt.estimate_image(img, cam, [name])[0]
        assert c.ok and c.confidence >= alone.conf.verify_below
        assert (d.status, d.reason) == (c.status, c.reason)
        np.testing.assert_array_equal(d.cam_from_model, c.cam_from_model)


def test_a_worker_loads_a_second_library_only_when_it_is_asked_for(cracker_library, tmp_path):
    """The workers' second libraries load on first use: naming a folder reads nothing (a missing one fails
    only when asked for, with the error that names it), and a library asked for twice is loaded once."""
    from batchpose.errors import DataError  # noqa: PLC0415
    from batchpose.stages.estimate import LazyLibraries  # noqa: PLC0415

    libs = LazyLibraries({"cracker": str(cracker_library.folder), "gone": str(tmp_path / "gone")})
    assert len(libs) == 2 and "gone" in libs and "other" not in libs and list(libs) == ["cracker", "gone"]
    first = libs["cracker"]
    np.testing.assert_array_equal(first.desc, cracker_library.desc)
    assert libs["cracker"] is first
    with pytest.raises(DataError, match="gone: template library is unreadable"):
        libs["gone"]


def shifted(library, model):
    """The library with its 3D points moved 0.3 d along the model's x axis: it matches as well as ever, to a
    confident pose 0.3 d beside the box, whose outline the frame does not show."""
    move = np.array([0.3 * model.diameter_m, 0.0, 0.0], dtype=np.float32)
    return dataclasses.replace(library, pts3d=library.pts3d + move)


def test_a_pose_the_verification_score_rejects_is_retried_and_the_retry_is_scored(cracker_model, cracker_library):
    """``retry_rejected``: a confident first pose the verification score rejects gives the object the second
    library, whose pose (within 0.1 d) passes the same score, and the record says both; without the option,
    or without a second library, the rejected pose stays low_confidence; a retry's pose the score rejects
    too is low_confidence, its reason naming both scores."""
    from tests.test_track import frame_of  # noqa: PLC0415

    name = cracker_model.name
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    wrong = shifted(cracker_library, cracker_model)
    rescued = estimator(cracker_model, wrong, cracker_library)
    kept = estimator(cracker_model, wrong, cracker_library, retry_rejected=False)
    alone = estimator(cracker_model, wrong)
    twice = estimator(cracker_model, wrong, wrong)
    assert has_retries(rescued.objects, name) and not has_retries(alone.objects, name)  # alone: no SIFT again
    rng = np.random.default_rng(5)
    for k in range(2):
        T = random_pose(rng, cracker_model.center_m)
        frame = frame_of(compose(rng, cracker_model, T), k)
        (a,) = alone.estimate_frame(frame, [name])
        assert a.status == "low_confidence" and a.confidence >= alone.conf.verify_below, (a.status, a.reason)
        assert "min_verification" in a.reason and add_error(a.cam_from_model, T, pts) > 0.2 * cracker_model.diameter_m
        (b,) = rescued.estimate_frame(frame, [name])
        assert b.ok and b.verification >= rescued.conf.min_verification, (b.status, b.reason)
        assert b.reason.startswith("found with the lit templates, after the verification score rejected"), b.reason
        assert add_error(b.cam_from_model, T, pts) < 0.1 * cracker_model.diameter_m
        (c,) = kept.estimate_frame(frame, [name])
        assert (c.status, c.reason) == (a.status, a.reason)
    (d,) = twice.estimate_frame(frame, [name])  # the retry's pose is rejected too: the record says both
    assert d.status == "low_confidence", (d.status, d.reason)
    both = (
        r"found with the lit templates, after the verification score rejected the first pose \(0\.\d\d\); "
        r"verification 0\.\d\d < min_verification 0\.5 \(outline .*\)"
    )
    assert re.fullmatch(both, d.reason), d.reason

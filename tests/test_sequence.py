"""The memory of a sequence of frames (batchpose.method.sequence): which frame follows which, and a Sequence
that survives a pickle round trip (a worker's checkpoint) to give exactly the records it would have given."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest

from batchpose.core.frames import Camera
from batchpose.method.features import to_gray
from batchpose.method.render import get_renderer
from batchpose.method.sequence import PreviousFrame, SearchPose, Sequence, Stamp, follows, is_next, previous_pose
from batchpose.method.track import Track
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import textured_background
from tests.test_track import PERIOD_NS, clip_pose, frame_of, make_estimator


def test_the_next_frame_is_one_image_id_on_in_the_same_scene_and_camera_a_moment_later():
    """is_next: im_id + im_step, same scene and K, 0 < gap <= max_gap_s. follows (tracking) adds the image
    size and the distortion; the searches' previous_pose uses is_next alone."""
    img = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    f0 = frame_of(img, 0)
    stamp = Stamp.of(f0)
    assert is_next(stamp, frame_of(img, 1), 0.25)
    assert not is_next(stamp, frame_of(img, 2), 0.25)  # an image skipped
    assert is_next(stamp, dataclasses.replace(frame_of(img, 2), im_step=2), 0.25)
    assert not is_next(stamp, frame_of(img, 1, scene_id=1), 0.25)
    assert not is_next(stamp, frame_of(img, 1, stamp_ns=1_000_000_000), 0.25)  # 1 s later
    assert not is_next(stamp, frame_of(img, 1, stamp_ns=0), 0.25)  # not later at all
    other_K = dataclasses.replace(frame_of(img, 1), camera=Camera(K_SYN * [[1.01], [1], [1]], 640, 480))
    assert not is_next(stamp, other_K, 0.25)

    previous = PreviousFrame(stamp, to_gray(img), np.zeros(0))
    assert follows(previous, frame_of(img, 1), 0.25) and not follows(None, frame_of(img, 1), 0.25)
    lens = dataclasses.replace(frame_of(img, 1), camera=Camera(K_SYN, 640, 480, dist=np.array([-0.2, 0, 0, 0, 0])))
    assert is_next(stamp, lens, 0.25) and not follows(previous, lens, 0.25)
    smaller = dataclasses.replace(frame_of(img, 1), camera=Camera(K_SYN, 320, 240))
    assert is_next(stamp, smaller, 0.25) and not follows(previous, smaller, 0.25)

    pose = np.eye(4)
    store = {"box": SearchPose(stamp, pose)}
    assert previous_pose(store, "box", lens, 0.25) is pose
    assert previous_pose(store, "box", frame_of(img, 2), 0.25) is None
    assert previous_pose(store, "can", lens, 0.25) is None


def test_a_sequence_pickles_whole_and_forgets_everything():
    rng = np.random.default_rng(1)
    gray = rng.integers(0, 255, (48, 64), dtype=np.uint8)
    stamp = Stamp(3, 7, 7 * PERIOD_NS, K_SYN.copy())
    xy = rng.random((20, 2)).astype(np.float32)
    track = Track(xy, rng.random((20, 3)), np.eye(4), 20, 0.8, 2, gray, xy.copy(), np.eye(4))
    seq = Sequence(
        tracks={"box": track},
        lost={"can": 3},
        last={"box": np.eye(4), "can": 2 * np.eye(4)},
        previous=PreviousFrame(stamp, gray, np.zeros(5)),
        found={"can": SearchPose(stamp, 3 * np.eye(4))},
        placed={"jar": SearchPose(stamp, 4 * np.eye(4))},
    )
    copy = pickle.loads(pickle.dumps(seq))
    for f in dataclasses.fields(Sequence):
        np.testing.assert_equal(dataclasses.asdict(copy)[f.name], dataclasses.asdict(seq)[f.name])
    seq.forget()
    assert seq == Sequence()


@pytest.fixture(scope="module")
def clip_with_a_late_box(cracker_model):
    """Two frames of background, then seven of the moving box over it (sensor noise): RGB images."""
    rng = np.random.default_rng(13)
    bg = textured_background(rng)
    out = [bg, bg.copy()]
    for i in range(7):
        T = clip_pose(i, cracker_model.center_m)
        rgb, depth = get_renderer().render(cracker_model.content_hash, cracker_model.mesh, T, K_SYN, 640, 480, "lit")
        img = bg.copy()
        img[depth > 0] = rgb[depth > 0]
        out.append(np.clip(img.astype(np.float32) + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8))
    return out


def _row(rec) -> dict:
    return {k: v for k, v in rec.to_row().items() if not k.startswith("time_")}


def test_a_pickled_sequence_continues_exactly_as_the_original(cracker_model, cracker_library, clip_with_a_late_box):
    """Four frames into a tracked sequence (the box lost twice, found, then tracked), the Sequence is pickled
    as a worker's checkpoint would; the original and the unpickled copy (in a new estimator, as a resumed
    worker has) then estimate the same five frames, with a refresh among them: identical records."""
    name = cracker_model.name
    frames = [frame_of(img, i) for i, img in enumerate(clip_with_a_late_box)]
    est = make_estimator(cracker_model, cracker_library, refresh_every=3)
    seq = Sequence()
    before = [est.estimate_frame(f, [name], seq)[0] for f in frames[:4]]
    assert [r.ok for r in before] == [False, False, True, True] and before[-1].tracked
    assert seq.lost[name] == 4 and seq.tracks and name in seq.last  # a young track: still counted as lost
    saved = pickle.dumps(seq)
    kept = [est.estimate_frame(f, [name], seq)[0] for f in frames[4:]]
    copy = pickle.loads(saved)
    resumed = make_estimator(cracker_model, cracker_library, refresh_every=3)
    again = [resumed.estimate_frame(f, [name], copy)[0] for f in frames[4:]]
    assert all(r.ok and r.tracked for r in kept)
    assert any(r.timings["seed"] > 0 for r in kept)  # a refresh happened after the checkpoint
    for a, b in zip(kept, again, strict=True):
        np.testing.assert_equal(_row(b), _row(a))
    for f in dataclasses.fields(Sequence):
        np.testing.assert_equal(dataclasses.asdict(copy)[f.name], dataclasses.asdict(seq)[f.name])

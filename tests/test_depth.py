"""Depth images (``depth.enabled``): decoding, the readers, the check and alignment of a pose, the estimator."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import scipy.io

from batchpose.config import ConfigError, DepthConfig, EstimatorConfig, from_dict, load_estimator_config
from batchpose.core.frames import Camera, Frame, decode_depth
from batchpose.errors import ImageError
from batchpose.io.bop_csv import poses_to_bop
from batchpose.io.folders import BopFrameSource, YcbvFrameSource
from batchpose.method.depth import Surface, align_to_depth
from batchpose.method.estimator import PoseEstimator
from batchpose.method.render import get_renderer
from batchpose.method.sequence import Sequence
from tests.conftest import K_SYN
from tests.test_datasets import make_bop, make_ycbv
from tests.test_estimate_synthetic import compose

CAM = Camera(K_SYN, 640, 480)


def _frame(depth_format: str, data: bytes, scale: float = 1e-4, step: int = 0, w: int = 4, h: int = 3) -> Frame:
    return Frame(
        "f", 0, 0, 0, Camera(np.eye(3), w, h), "png", b"x",
        depth_format=depth_format, depth_data=data, depth_scale_m=scale, depth_step=step,
    )  # fmt: skip


def test_decode_depth_encodings():
    mm = np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000
    png = cv2.imencode(".png", mm)[1].tobytes()
    np.testing.assert_allclose(decode_depth(_frame("png", png, scale=1e-3)), mm / 1000.0, rtol=1e-6)
    padded = np.zeros((3, 6), np.uint16)  # rows of 12 bytes, 8 used
    padded[:, :4] = mm
    np.testing.assert_allclose(decode_depth(_frame("16UC1", padded.tobytes(), 1e-3, step=12)), mm / 1000.0, rtol=1e-6)
    metres = (mm / 1000.0).astype(np.float32)
    metres[0, 1] = np.nan  # no reading
    out = decode_depth(_frame("32FC1", metres.tobytes(), 1.0))
    assert out.dtype == np.float32 and out[0, 1] == 0.0 and out[2, 3] == pytest.approx(11.0)
    assert decode_depth(_frame("", b"")) is None


@pytest.mark.parametrize(
    "frame, match",
    [
        (_frame("32FC3", b"x" * 144), "unsupported depth encoding '32FC3'"),
        (_frame("png", b""), "depth image is empty"),
        (_frame("png", b"not a png"), "depth PNG must be single-channel 16-bit, got undecodable"),
        (
            _frame("png", cv2.imencode(".png", np.zeros((3, 4), np.uint8))[1].tobytes()),
            "single-channel 16-bit, got uint8",
        ),
        (_frame("png", cv2.imencode(".png", np.zeros((5, 4), np.uint16))[1].tobytes()), "depth image is 4x5"),
        (_frame("16UC1", b"\0" * 20), r"raw 16UC1 depth of 4x3 \(step 8\) needs 24 bytes, got 20"),
        (_frame("16UC1", b"\0" * 24, scale=0.0), "depth scale must be a positive number"),
        (_frame("compressedDepth rvl 16UC1", b"\0" * 40), "unsupported depth encoding 'compressedDepth rvl 16UC1'"),
        (_frame("compressedDepth png 32FC1", b"\0" * 12), "compressedDepth image of 12 bytes has no PNG after"),
    ],
)
def test_decode_depth_rejects_bad_input(frame, match):
    with pytest.raises(ImageError, match=match):
        decode_depth(frame)


def test_ycbv_and_bop_readers_attach_depth(tmp_path):
    make_ycbv(tmp_path / "ycbv")
    mm = np.full((24, 32), 12345, np.uint16)
    cv2.imwrite(str(tmp_path / "ycbv/data/0001/000001-depth.png"), mm)
    meta = tmp_path / "ycbv/data/0001/000001-meta.mat"
    m = scipy.io.loadmat(str(meta))
    scipy.io.savemat(meta, {k: v for k, v in m.items() if not k.startswith("__")} | {"factor_depth": 10000})
    frames = list(YcbvFrameSource(tmp_path / "ycbv"))
    assert frames[0].has_depth and not frames[1].has_depth  # the second frame has no -depth.png
    np.testing.assert_allclose(decode_depth(frames[0]), 1.2345, rtol=1e-6)

    make_bop(tmp_path / "bop")
    (tmp_path / "bop/000048/depth").mkdir()
    cv2.imwrite(str(tmp_path / "bop/000048/depth/000001.png"), mm)  # depth_scale 0.1: 0.1 mm per unit
    frames = list(BopFrameSource(tmp_path / "bop"))
    assert frames[0].has_depth and not frames[1].has_depth
    np.testing.assert_allclose(decode_depth(frames[0]), 1.2345, rtol=1e-6)
    cams = json.loads((tmp_path / "bop/000048/scene_camera.json").read_text())
    cams["1"]["depth_scale"] = -1
    (tmp_path / "bop/000048/scene_camera.json").write_text(json.dumps(cams))
    with pytest.raises(Exception, match="depth_scale must be a positive number, got -1"):
        BopFrameSource(tmp_path / "bop")


def test_depth_config_is_checked():
    with pytest.raises(ConfigError, match="depth.gate_final_m must be positive and at most gate_m"):
        load_estimator_config({"depth": {"gate_m": 0.01, "gate_final_m": 0.02}})
    with pytest.raises(ConfigError, match="unknown key gate"):
        from_dict(EstimatorConfig, {"depth": {"gate": 0.1}})


def _scene_depth(model, T, wall_m: float = 1.5) -> np.ndarray:
    """The mesh at T in front of a wall ``wall_m`` away, as a depth sensor would see it."""
    _, d = get_renderer().render(model.content_hash, model.mesh, T, K_SYN, 640, 480)
    return np.where(d > 0, d, wall_m).astype(np.float32)


def _renders_depth(model):
    return lambda T: get_renderer().render(model.content_hash, model.mesh, T, K_SYN, 640, 480)[1]


def _pose(model) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([2.2, 0.4, -0.3]))[0]
    T[:3, 3] = np.array([0.02, -0.01, 0.8]) - T[:3, :3] @ model.center_m
    return T


def _moved(T, model, along_ray: float, turn_deg: float) -> np.ndarray:
    """T with the object's centre moved ``along_ray`` (fraction) along its viewing ray and turned."""
    out = T.copy()
    c = T[:3, :3] @ model.center_m + T[:3, 3]
    R = cv2.Rodrigues(np.deg2rad([turn_deg, 0.0, 0.0]))[0] @ T[:3, :3]
    out[:3, :3] = R
    out[:3, 3] = c * (1 + along_ray) - R @ model.center_m
    return out


def _add_mm(model, A, B) -> float:
    pts = np.asarray(model.mesh.vertices)[::8]
    return 1000 * float(np.linalg.norm((pts @ A[:3, :3].T + A[:3, 3]) - (pts @ B[:3, :3].T + B[:3, 3]), axis=1).mean())


def test_alignment_recovers_the_distance_a_monocular_pose_gets_wrong(cracker_model):
    T = _pose(cracker_model)
    depth = _scene_depth(cracker_model, T)
    rng = np.random.default_rng(0)
    noisy = depth + rng.normal(0, 0.002, depth.shape).astype(np.float32)  # 2 mm sensor noise
    noisy[rng.random(depth.shape) < 0.1] = 0  # and holes
    start = _moved(T, cracker_model, 0.04, 4.0)  # 3.2 cm too far, turned 4 degrees
    surface = Surface.of(cracker_model.mesh)
    fit = align_to_depth(
        start, noisy, _renders_depth(cracker_model), K_SYN, surface, cracker_model.diameter_m, DepthConfig()
    )
    assert fit.aligned and not fit.contradicted and fit.reason == ""
    assert _add_mm(cracker_model, start, T) > 25
    assert _add_mm(cracker_model, fit.cam_from_model, T) < 2.0
    assert fit.see_through < 0.2 and fit.agree > 0.9


def test_poses_the_depth_contradicts(cracker_model):
    T = _pose(cracker_model)
    surface, conf = Surface.of(cracker_model.mesh), DepthConfig()

    def fit_at(T_est, depth):
        return align_to_depth(
            T_est, depth, _renders_depth(cracker_model), K_SYN, surface, cracker_model.diameter_m, conf
        )

    wall = np.full((480, 640), 1.5, np.float32)  # the object is not there at all
    floating = fit_at(T, wall)
    assert floating.contradicted and "sees more than 3 cm past it" in floating.reason
    behind = fit_at(_moved(T, cracker_model, 1.2, 0.0), _scene_depth(cracker_model, T, wall_m=1.0))
    assert behind.contradicted and "only 0% of the object's pixels have a reading within" in behind.reason
    near_miss = _moved(T, cracker_model, 0.0, 0.0)
    near_miss[:3, 3] += [0.03, 0.0, 0.0]  # 3 cm sideways (11 % of its diameter): aligned, then checked
    rescued = fit_at(near_miss, _scene_depth(cracker_model, T))
    assert rescued.aligned and not rescued.contradicted
    assert _add_mm(cracker_model, rescued.cam_from_model, T) < 2.0
    # 10 m away: 155 readings on it, too few to align with min_pixels 200, enough to see it is behind the wall.
    far = align_to_depth(
        _moved(T, cracker_model, 12.0, 0.0),
        _scene_depth(cracker_model, T),
        _renders_depth(cracker_model),
        K_SYN,
        surface,
        cracker_model.diameter_m,
        DepthConfig(min_pixels=200),
    )
    assert far.contradicted and "only 0% of the object's pixels have a reading within" in far.reason
    blind = fit_at(T, np.zeros((480, 640), np.float32))  # no readings: nothing to say
    assert (
        not blind.contradicted and not blind.aligned and "0 of the object's pixels have a depth reading" in blind.reason
    )


def test_estimator_aligns_its_poses_to_the_depth_image(cracker_model, cracker_library):
    """The real-frame case: the image shows the object 4 % farther than the depth does (the mesh and the
    real object differ in size). RGB alone finds the image's pose; with depth.enabled, the depth's."""
    T = _pose(cracker_model)
    T_image = _moved(T, cracker_model, 0.04, 0.0)
    rgb = compose(np.random.default_rng(1), cracker_model, T_image)
    depth_mm = (_scene_depth(cracker_model, T) * 1000).astype(np.uint16)

    def frame(depth_bytes: bytes) -> Frame:
        return Frame(
            "syn", 0, 0, 0, CAM, "png", cv2.imencode(".png", rgb[:, :, ::-1])[1].tobytes(),
            depth_format="png", depth_data=depth_bytes, depth_scale_m=0.001,
        )  # fmt: skip

    good = frame(cv2.imencode(".png", depth_mm)[1].tobytes())
    results = {}
    for enabled in (False, True):
        conf = load_estimator_config({"depth": {"enabled": enabled}, "track": {"enabled": False}})
        est = _estimator(conf, cracker_model, cracker_library)
        (rec,) = est.estimate_frame(good, [cracker_model.name])
        assert rec.ok
        results[enabled] = _add_mm(cracker_model, rec.cam_from_model, T)
        if enabled:
            assert rec.timings["depth"] > 0 and rec.reason == ""
            (bad,) = est.estimate_frame(frame(b"corrupt"), [cracker_model.name])
            assert bad.ok and bad.reason.startswith("depth image not used (syn (depth): depth PNG must be")
    assert results[False] > 20  # ~3 cm: where the image puts it
    assert results[True] < 3


def test_a_pose_below_min_confidence_is_not_reported_unless_the_depth_vouches_for_it(cracker_model, cracker_library):
    """estimator.min_confidence: an RGB pose less confident is status low_confidence (pose kept for inspection,
    never in poses.csv); with depth.enabled, the depth image aligning it makes it ok."""
    T = _pose(cracker_model)
    rgb, depth = _search_scene(cracker_model, T)
    frame = _rgbd_frame(rgb, depth)
    recs = {}
    for enabled in (False, True):
        conf = load_estimator_config(
            {"min_confidence": 0.999, "depth": {"enabled": enabled}, "track": {"enabled": False}}
        )
        (recs[enabled],) = _estimator(conf, cracker_model, cracker_library).estimate_frame(frame, [cracker_model.name])
    low = recs[False]
    assert low.status == "low_confidence" and 0.5 < low.confidence < 0.999
    assert low.reason.startswith(f"confidence {low.confidence:.2f} below estimator.min_confidence 0.999 (")
    assert _adds_mm(cracker_model, low.cam_from_model, T) < 10  # kept in poses.parquet
    assert poses_to_bop(pd.DataFrame([low.to_row()])).empty
    vouched = recs[True]
    assert vouched.ok and vouched.reason == f"RGB confidence {vouched.confidence:.2f}, aligned to the depth image"
    assert _adds_mm(cracker_model, vouched.cam_from_model, T) < 5


def test_shared_ycbv_dev_depth_frames_decode():
    root = Path(__file__).resolve().parents[2] / "shared" / "data" / "ycbv_dev"
    if not root.is_dir():
        pytest.skip(f"shared YCB-Video dev data not at {root}")
    f = next(iter(YcbvFrameSource(root)))
    d = decode_depth(f)
    assert f.depth_scale_m == pytest.approx(1e-4) and d.shape == (480, 640)
    assert 0.3 < float(np.median(d[d > 0])) < 3.0  # metres


# ------------------------------------------------------------------------------------------------ MCAP


def _raw_depth(t_header: int, mm: np.ndarray, encoding: str = "16UC1", frame_id: str = "cam_optical"):
    """Depth registered to tests.test_mcap_io's images: in their camera frame, ``cam_optical``."""
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    data = mm.astype("<u2") if encoding == "16UC1" else (mm / 1000.0).astype("<f4")
    m = RawImage(
        frame_id=frame_id,
        width=mm.shape[1],
        height=mm.shape[0],
        encoding=encoding,
        step=data.strides[0],
        data=data.tobytes(),
    )
    m.timestamp.FromNanoseconds(t_header)
    return m


def test_mcap_depth_topic_pairs_by_header_stamp(tmp_path):
    """Depth logged after its image and a few ms off is paired; a depth 40 ms away is not anyone's."""
    from batchpose.io.sources import open_frames
    from tests.test_mcap_io import DT, T0, H, Log, W, _calib, _cimg, _enc, _img

    rng = np.random.default_rng(0)
    log_ = Log(tmp_path / "rgbd.mcap")
    depths = {}
    for i in range(4):
        t = T0 + i * DT
        log_.proto("/cam/calibration", _calib(t), t)
        log_.proto("/cam/image", _cimg(t, _enc(_img(rng), ".png"), "png"), t)
        mm = np.full((H, W), 500 + 100 * i, np.uint16)
        if i == 2:  # this image's depth is 40 ms off: no pair
            log_.proto("/cam/depth", _raw_depth(t + 40_000_000, mm), t + 3)
        else:  # logged after the image, stamped 5 ms later (float metres for the last one)
            log_.proto("/cam/depth", _raw_depth(t + 5_000_000, mm, "32FC1" if i == 3 else "16UC1"), t + 2)
            depths[i] = mm / 1000.0
    log_.close()
    plain = list(open_frames({"format": "mcap", "path": str(tmp_path / "rgbd.mcap")}, tmp_path))
    assert len(plain) == 4 and not any(f.has_depth for f in plain)  # no depth_topic: no depth
    frames = list(
        open_frames({"format": "mcap", "path": str(tmp_path / "rgbd.mcap"), "depth_topic": "/cam/depth"}, tmp_path)
    )
    assert [f.has_depth for f in frames] == [True, True, False, True]
    assert [f.image_data for f in frames] == [f.image_data for f in plain]
    for i, mm in depths.items():
        np.testing.assert_allclose(decode_depth(frames[i]), mm, rtol=1e-6)
    with pytest.raises(Exception, match="depth topic '/cam/nope' not found"):
        open_frames({"format": "mcap", "path": str(tmp_path / "rgbd.mcap"), "depth_topic": "/cam/nope"}, tmp_path)


def _compressed_depth(depth_m: np.ndarray, encoding: str) -> bytes:
    """What ROS's compressed_depth_image_transport publishes with its default parameters (PNG inside)."""
    if encoding == "32FC1":  # quantised inverse depth, depth_quantization 100, depth_max 10 m
        a = np.float32(100.0 * 101.0)
        b = np.float32(1.0) - a / np.float32(10.0)
        inv = a / np.maximum(depth_m, 1e-3).astype(np.float32) + b
        q = np.where((depth_m > 0) & (depth_m < 10), inv, 0).astype(np.uint16)
        return struct.pack("<iff", 0, a, b) + cv2.imencode(".png", q)[1].tobytes()
    mm = np.round(depth_m * 1000).astype(np.uint16)
    return struct.pack("<iff", 0, 0.0, 0.0) + cv2.imencode(".png", mm)[1].tobytes()


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_ros_compressed_depth_topic(tmp_path, encoding):
    """A ROS 1 log with its depth on .../compressedDepth (format "16UC1; compressedDepth png" or 32FC1's
    quantised inverse depth): read to the millimetre, and no reading stays none."""
    from batchpose.io.sources import open_frames
    from tests.test_mcap_io import DT, ROS1, T0, H, W, ros1_camera_info, ros1_header, ros1_image, ros1_log
    from tests.test_mcap_io import ros1_record as rec

    depth = np.random.default_rng(8).uniform(0.4, 3.0, (H, W))
    depth[5, 7] = 0.0  # no reading
    records = []
    for i in range(2):
        t = T0 + i * DT
        fmt = f"{encoding}; compressedDepth" + (" png" if i else "")  # the oldest versions wrote no codec
        msg = ROS1["sensor_msgs/CompressedImage"](header=ros1_header(t), format=fmt)
        msg.data = _compressed_depth(depth, encoding)
        records += [
            rec("/camera/color/camera_info", ros1_camera_info(t), t),
            rec("/camera/color/image_raw", ros1_image(t, np.zeros((H, W), np.uint8), "mono8"), t),
            rec("/camera/depth/image_raw/compressedDepth", msg, t + 1),
        ]
    ros1_log(tmp_path / "rgbd.mcap", records)
    spec = {"format": "mcap", "path": "rgbd.mcap", "depth_topic": "/camera/depth/image_raw/compressedDepth"}
    frames = list(open_frames(spec, tmp_path))
    assert [f.depth_format for f in frames] == [f"compressedDepth png {encoding}"] * 2
    for f in frames:
        out = decode_depth(f)
        assert out[5, 7] == 0.0
        # 16UC1 holds whole millimetres; 32FC1's inverse depth steps are depth^2 / 10100 m (0.9 mm at 3 m)
        np.testing.assert_allclose(out, depth, atol=0.5e-3 if encoding == "16UC1" else 0.9e-3)


def test_mcap_depth_in_another_camera_frame_is_refused(tmp_path):
    """A RealSense log's depth/image_rect_raw is the depth camera's own image, not registered to the colour
    one; used as depth_topic it would put every depth reading at the wrong pixel."""
    from batchpose.errors import DataError
    from batchpose.io.sources import open_frames
    from tests.test_mcap_io import T0, H, Log, W, _calib, _cimg, _enc, _img

    log_ = Log(tmp_path / "d435.mcap")
    log_.proto("/cam/calibration", _calib(T0), T0)
    log_.proto("/cam/image", _cimg(T0, _enc(_img(np.random.default_rng(0)), ".png"), "png"), T0)
    log_.proto("/cam/depth_raw", _raw_depth(T0, np.full((H, W), 700, np.uint16), frame_id="depth_optical"), T0 + 1)
    log_.close()
    spec = {"format": "mcap", "path": "d435.mcap", "depth_topic": "/cam/depth_raw"}
    with pytest.raises(DataError, match=r"/cam/depth_raw: depth images are in frame 'depth_optical', the images on "
                       r"/cam/image in 'cam_optical'; the depth must be registered to the colour camera"):  # fmt: skip
        list(open_frames(spec, tmp_path))


def test_convert_writes_depth_and_the_image_topic_stays_the_image(tmp_path):
    """A folder data set with depth converts to /camera/image + /camera/depth (16UC1, mm); reading the log
    back picks the image topic, not the depth, and the depth round-trips to the millimetre."""
    from batchpose.io.mcap_write import write_frames_mcap
    from batchpose.io.sources import open_frames

    make_ycbv(tmp_path / "ycbv")
    tenths = np.random.default_rng(3).integers(3000, 30000, (24, 32)).astype(np.uint16)  # YCB-Video: 0.1 mm
    for rel in ("data/0001/000001", "data/0001/000002", "data_syn/000007"):
        cv2.imwrite(str(tmp_path / f"ycbv/{rel}-depth.png"), tenths)
        meta = tmp_path / f"ycbv/{rel}-meta.mat"
        m = {k: v for k, v in scipy.io.loadmat(str(meta)).items() if not k.startswith("__")}
        scipy.io.savemat(meta, m | {"factor_depth": 10000})
    src = list(YcbvFrameSource(tmp_path / "ycbv"))
    write_frames_mcap(src, tmp_path / "out.mcap")
    spec = {"format": "mcap", "path": str(tmp_path / "out.mcap"), "depth_topic": "/camera/depth"}
    back = list(open_frames(spec, tmp_path))
    assert [f.image_data for f in back] == [f.image_data for f in src]
    for f in back:
        assert f.depth_format == "16UC1"
        np.testing.assert_allclose(decode_depth(f), tenths / 10000.0, atol=0.5e-3 + 1e-6)  # to the millimetre


# ------------------------------------------------------------------------------------- depth.search


def _search_scene(model, T, seed: int = 5):
    """The object lit at T over colour blobs (rgb), in front of a wall 1.5 m away (depth)."""
    return compose(np.random.default_rng(seed), model, T), _scene_depth(model, T)


def _search(model, library, rgb, depth):
    from batchpose.method.depth_search import Silhouettes, search

    r = get_renderer()
    conf = DepthConfig(search=True)
    sil = Silhouettes.of(
        lambda T: r.render(model.content_hash, model.mesh, T, library.K, library.width, library.height),
        library,
        model.diameter_m,
        conf.search_view_step,
    )
    return search(
        rgb,
        depth,
        K_SYN,
        library,
        sil,
        Surface.of(model.mesh),
        model.flips(),
        model.diameter_m,
        lambda T: r.render(model.content_hash, model.mesh, T, K_SYN, 640, 480),
        conf,
    )


def _adds_mm(model, A, B) -> float:
    from scipy.spatial import cKDTree

    pts = np.asarray(model.mesh.vertices)[::8]
    return 1000 * float(cKDTree(pts @ A[:3, :3].T + A[:3, 3]).query(pts @ B[:3, :3].T + B[:3, 3])[0].mean())


def _estimator(conf, model, library) -> PoseEstimator:
    return PoseEstimator(conf, {model.name: library}, models={model.name: model}, renderer=get_renderer())


def _rgbd_frame(rgb, depth, im_id: int = 0) -> Frame:
    """One frame of a 30 Hz sequence with its depth (32FC1, metres)."""
    return Frame(
        "syn", 0, im_id, im_id * 33_000_000, CAM, "png", cv2.imencode(".png", rgb[:, :, ::-1])[1].tobytes(),
        depth_format="32FC1", depth_data=depth.astype("<f4").tobytes(), depth_scale_m=1.0,
    )  # fmt: skip


def test_depth_search_finds_the_object_by_colour_and_depth(cracker_model, cracker_library):
    T = _pose(cracker_model)
    rgb, depth = _search_scene(cracker_model, T)
    found = _search(cracker_model, cracker_library, rgb, depth)
    assert found is not None and found.visible > 0.8 and found.see_through < 0.05
    assert _adds_mm(cracker_model, found.cam_from_model, T) < 10


def test_depth_search_finds_an_object_half_hidden_behind_a_nearer_one(cracker_model, cracker_library):
    """The box's lower half behind a grey slab 15 cm nearer: the alignment alone settles on a pose that fits
    the visible half badly; the polish (turns, judged on the unhidden pixels only) finds the box."""
    T = _pose(cracker_model)
    rgb, depth = _search_scene(cracker_model, T)
    _, d = get_renderer().render(cracker_model.content_hash, cracker_model.mesh, T, K_SYN, 640, 480)
    ys = np.nonzero(d > 0)[0]
    cut = (ys.min() + ys.max()) // 2
    rgb[cut:] = 128
    depth[cut:] = np.where(d[cut:] > 0, d[cut:] - 0.15, 0.6)
    found = _search(cracker_model, cracker_library, rgb, depth)
    assert found is not None and 0.4 < found.visible < 0.6  # the hidden half is not counted as seen
    assert _adds_mm(cracker_model, found.cam_from_model, T) < 10


def test_depth_search_finds_nothing_where_the_object_is_not(cracker_model, cracker_library):
    """The same scene with another box (the gelatin box) where the cracker box was: nothing is kept."""
    from batchpose.io.mesh import load_mesh
    from tests.conftest import GELATIN

    other = load_mesh(GELATIN)
    T = _pose(other)
    rgb, depth = _search_scene(other, T)
    assert _search(cracker_model, cracker_library, rgb, depth) is None


def test_estimator_depth_search_replaces_a_missing_pose(cracker_model, cracker_library):
    """SIFT starved (4 keypoints a frame): no RGB pose; with depth.search the object is found, and says so."""
    T = _pose(cracker_model)
    rgb, depth = _search_scene(cracker_model, T)
    frame = _rgbd_frame(rgb, depth)
    for search in (False, True):
        conf = load_estimator_config(
            {"features": {"n_features": 4}, "track": {"enabled": False}, "depth": {"enabled": True, "search": search}}
        )
        est = _estimator(conf, cracker_model, cracker_library)
        (rec,) = est.estimate_frame(frame, [cracker_model.name])
        if not search:
            assert not rec.ok
        else:
            assert rec.ok and rec.reason.startswith("found by the depth search (no SIFT pose)")
            assert 0 < rec.confidence <= 0.5 and rec.timings["depth"] > 0
            assert _adds_mm(cracker_model, rec.cam_from_model, T) < 10


def test_depth_search_follows_its_pose_into_the_next_frame(cracker_model, cracker_library):
    """With tracking on, the next frame of a sequence starts from the pose the search found (the object
    moved 1 cm): aligned and polished, not searched for again; a frame that does not follow is searched."""
    conf = load_estimator_config({"features": {"n_features": 4}, "depth": {"enabled": True, "search": True}})
    est = _estimator(conf, cracker_model, cracker_library)
    T0 = _pose(cracker_model)
    T1 = T0.copy()
    T1[:3, 3] += [0.01, 0.0, 0.0]
    reasons, seq = [], Sequence()
    for im_id, T in [(0, T0), (1, T1), (3, T0)]:
        rgb, depth = _search_scene(cracker_model, T)
        (rec,) = est.estimate_frame(_rgbd_frame(rgb, depth, im_id), [cracker_model.name], seq)
        assert rec.ok and _adds_mm(cracker_model, rec.cam_from_model, T) < 10
        reasons.append(rec.reason.split(" (")[0])
    assert reasons == [
        "found by the depth search",
        "followed from the previous frame's depth search",
        "found by the depth search",
    ]


def test_depth_search_for_a_lost_object_only_with_its_full_estimates(cracker_model, cracker_library, monkeypatch):
    """With tracking on, an object lost since earlier frames (here: absent) is searched for only in the
    frames where its RGB estimate is a full one (every track.lost_full_every-th), not in every frame."""
    from batchpose.io.mesh import load_mesh
    from tests.conftest import GELATIN

    other = load_mesh(GELATIN)
    conf = load_estimator_config(
        {"features": {"n_features": 4}, "track": {"lost_full_every": 3}, "depth": {"enabled": True, "search": True}}
    )
    est = _estimator(conf, cracker_model, cracker_library)
    from batchpose.method import with_depth

    searched, seq = [], Sequence()
    search = with_depth.search_missing
    monkeypatch.setattr(
        with_depth,
        "search_missing",
        lambda o, rec, frame, *a: searched.append(frame.im_id) or search(o, rec, frame, *a),
    )
    rgb, depth = _search_scene(other, _pose(other))
    for im_id in range(5):
        (rec,) = est.estimate_frame(_rgbd_frame(rgb, depth, im_id), [cracker_model.name], seq)
        assert not rec.ok
    assert searched == [0, 3]

"""What Foxglove shows of poses.mcap (batchpose.io.mcap_poses, mcap_ros_tf, mcap_topics.foxglove_layout and
stages.export_mcap): an object is drawn only at the images where it was found, ground truth beside it, a
status label per object, the run's own topics in its layout, and ``/tf`` for ROS logs."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import trimesh
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders
from mcap_ros1.decoder import DecoderFactory as Ros1Decoders
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2.decoder import DecoderFactory as Ros2Decoders
from mcap_ros2.writer import Writer as Ros2Writer
from scipy.spatial.transform import Rotation

from batchpose.core.model import ObjectModel
from batchpose.io.gltf import mesh_to_glb
from batchpose.io.mcap_poses import write_poses_mcap
from batchpose.io.mcap_read import McapFrameSource
from batchpose.io.mcap_ros_tf import ROS2_TF
from batchpose.io.sources import open_frames
from batchpose.stages import export_mcap, ingest
from tests.conftest import DEMO
from tests.test_mcap_io import (
    DT,
    K1,
    ROS_CAMERA_INFO,
    ROS_COMPRESSED,
    T0,
    H,
    W,
    _enc,
    _img,
    _pose,
    ros1_camera_info,
    ros1_image,
    ros1_log,
    ros1_record,
)

IMAGE = "/camera/color/image_raw/compressed"
INFO = "/camera/color/camera_info"
OPTICAL = "camera_color_optical_frame"
#: Header stamps trail the log times (a driver stamps at exposure): in-message stamps must be the header's.
LAG = 2_000_000
#: Per image: what each object's record says (None: no record, e.g. a frame the run did not estimate).
PLAN = {
    "box": ["ok", "ok", "too_few_matches", "hidden", "ok", None],
    "can": ["ok", "pnp_failed", "ok", "ok", "ok", "ok"],
}
N = 6


def _header(t: int, frame_id: str = OPTICAL) -> dict:
    s = t - LAG
    return {"stamp": {"sec": s // 1_000_000_000, "nanosec": s % 1_000_000_000}, "frame_id": frame_id}


def ros2_log(path: Path, n: int = N) -> Path:
    """A ROS 2 camera log as a RealSense driver records it: PNG CompressedImage and CameraInfo under
    ``/camera/color``, frame ``camera_color_optical_frame``, and an unrelated topic."""
    rng = np.random.default_rng(5)
    with open(path, "wb") as f:
        w = Ros2Writer(f)
        s_img = w.register_msgdef("sensor_msgs/msg/CompressedImage", ROS_COMPRESSED)
        s_info = w.register_msgdef("sensor_msgs/msg/CameraInfo", ROS_CAMERA_INFO)
        s_str = w.register_msgdef("std_msgs/msg/String", "string data\n")
        for i in range(n):
            t = T0 + i * DT
            w.write_message("/rosout_text", s_str, {"data": f"frame {i}"}, log_time=t - 10)
            info = {"header": _header(t), "height": H, "width": W, "distortion_model": "plumb_bob"}
            info |= {
                "d": [0.0] * 5,
                "k": K1.reshape(-1).tolist(),
                "p": np.hstack([K1, np.zeros((3, 1))]).ravel().tolist(),
            }
            w.write_message(INFO, s_info, info, log_time=t)
            img = {"header": _header(t), "format": "png", "data": _enc(_img(rng))}
            w.write_message(IMAGE, s_img, img, log_time=t, sequence=i)
        w.finish()
    return path


def plan_rows(stamps: list[int], plan: dict[str, list[str | None]], seed: int = 0) -> list[dict]:
    """poses.parquet-like rows following ``plan``; ok poses in front of the camera."""
    rng = np.random.default_rng(seed)
    rows = []
    for name, statuses in plan.items():
        for i, (s, status) in enumerate(zip(stamps, statuses, strict=True)):
            if status is None:
                continue
            T, ok = _pose(rng), status == "ok"
            rows.append(
                {
                    "frame_id": f"mcap:{s}",
                    "stamp_ns": s,
                    "obj_name": name,
                    "status": status,
                    "reason": "" if ok else "3 matches",
                    "R": T[:3, :3].ravel().tolist() if ok else [np.nan] * 9,
                    "t_m": T[:3, 3].tolist() if ok else [np.nan] * 3,
                    "confidence": 0.8 + 0.01 * i if ok else 0.0,
                    "n_inliers": 12 if ok else 0,
                    "inliers_px": [10.0, 12.0] if ok else [],
                    "tracked": ok and i == 1,
                }
            )
    return rows


def _messages(path: Path, decoders=()) -> list[tuple]:
    """(topic, log time, publish time, sequence, schema name, encoding, bytes, decoded or None) in file order,
    decoded by the first of ``decoders`` (mcap decoder factories) that reads the channel."""
    out, found = [], {}
    with open(path, "rb") as f:
        for s, ch, m in make_reader(f, validate_crcs=True).iter_messages():
            if ch.id not in found:
                found[ch.id] = next((d for fac in decoders if (d := fac.decoder_for(ch.message_encoding, s))), None)
            decode = found[ch.id]
            row = (ch.topic, m.log_time, m.publish_time, m.sequence, s.name if s else "", ch.message_encoding)
            out.append((*row, m.data, decode(m.data) if decode else None))
    return out


def _shown(scene: list[tuple[str, int, object]], t: int) -> dict[tuple[str, str], object]:
    """The entities Foxglove shows at time ``t`` after playing ``scene`` ((topic, log time, SceneUpdate)) in
    log-time order: per topic, an update's deletions first (matching id or all, of entities stamped earlier
    than the deletion), then its entities, each replacing the one of its id; an entity with a lifetime is
    gone once its stamp plus lifetime is past."""
    state: dict[tuple[str, str], object] = {}
    for topic, log_time, upd in sorted(scene, key=lambda m: m[1]):
        if log_time > t:
            break
        for d in upd.deletions:
            for key, e in list(state.items()):
                same = d.type == SceneEntityDeletion.ALL or key[1] == d.id
                if key[0] == topic and same and e.timestamp.ToNanoseconds() < d.timestamp.ToNanoseconds():
                    del state[key]
        for e in upd.entities:
            state[(topic, e.id)] = e
    live = {}
    for key, e in state.items():
        life = e.lifetime.ToNanoseconds()
        if life == 0 or e.timestamp.ToNanoseconds() + life >= t - LAG:
            live[key] = e
    return live


def _after_seek(scene: list[tuple[str, int, object]], t: int) -> dict[tuple[str, str], object]:
    """What Foxglove shows at ``t`` right after a seek: it reads only the last message of each topic."""
    last: dict[str, tuple] = {}
    for m in sorted(scene, key=lambda m: m[1]):
        if m[1] <= t:
            last[m[0]] = m
    return _shown(list(last.values()), t)


def _glb(extents) -> bytes:
    return mesh_to_glb(trimesh.creation.box(extents=extents))


@pytest.fixture(scope="module")
def ros2_written(tmp_path_factory):
    """A ROS 2 log and its poses.mcap, with the plan's records and ground truth of the box at every image
    but the fifth."""
    d = tmp_path_factory.mktemp("ros2")
    log_path = ros2_log(d / "in.mcap")
    stamps = [T0 + i * DT for i in range(N)]
    rows = plan_rows(stamps, PLAN)
    rng = np.random.default_rng(9)
    gt = [
        {"stamp_ns": s, "obj_name": "box", "R": (T := _pose(rng))[:3, :3].ravel(), "t_m": T[:3, 3]}
        for i, s in enumerate(stamps)
        if i != 4
    ]
    glbs = {"box": _glb((0.1, 0.2, 0.05)), "can": _glb((0.07, 0.07, 0.1))}
    out = d / "poses.mcap"
    written = write_poses_mcap(out, rows, glbs, input_mcap=log_path, ground_truth=gt)
    msgs = _messages(out, [ProtobufDecoders(), Ros2Decoders()])
    return log_path, out, written, rows, gt, glbs, msgs


def test_an_object_is_drawn_only_where_it_was_found(ros2_written):
    log_path, out, _, _, _, glbs, msgs = ros2_written
    scene = [(m[0], m[1], m[7]) for m in msgs if m[0].startswith("/batchpose/scene/")]
    assert {m[0] for m in scene} == {"/batchpose/scene/box", "/batchpose/scene/can"}
    for i in range(N):
        t = T0 + i * DT
        want = {name for name, plan in PLAN.items() if plan[i] == "ok"}
        shown = _shown(scene, t)
        assert {key[1] for key in shown} == want, (i, shown.keys())
        assert _after_seek(scene, t).keys() == shown.keys(), i  # a seek to this image shows the same
        for (_, name), e in shown.items():
            assert (e.frame_id, e.frame_locked) == (f"object/{name}", True)
            assert e.models[0].data == glbs[name] and not e.models[0].override_color
    # Just before the first image nothing is drawn; a mesh goes in once per run of images that find it.
    assert _shown(scene, T0 - 1) == {}
    entities = [(m[0], e.id) for m in scene for e in m[2].entities]
    assert sorted(entities) == [("/batchpose/scene/box", "box")] * 2 + [("/batchpose/scene/can", "can")] * 2


def test_the_input_log_is_copied_byte_for_byte(ros2_written):
    log_path, _, _, _, _, _, msgs = ros2_written
    kept = [m[:7] for m in msgs if not m[0].startswith("/batchpose/") and m[0] != "/tf"]
    assert kept == [m[:7] for m in _messages(log_path)]  # topic, times, sequence, schema, encoding, bytes


def test_status_and_confidence_label_every_object(ros2_written):
    _, _, _, _, _, _, msgs = ros2_written
    anns = [m for m in msgs if m[0] == "/batchpose/annotations"]
    assert [m[1] for m in anns] == [T0 + i * DT for i in range(N)]
    for i, m in enumerate(anns):
        texts = sorted(t.text for t in m[7].texts)
        want = []
        for name, plan in PLAN.items():
            if plan[i] == "ok":
                want.append(f"{name} ok {0.8 + 0.01 * i:.2f}" + (" tracked" if i == 1 else ""))
            elif plan[i] is not None:
                want.append(f"{name} {plan[i]} (3 matches)")
        assert texts == sorted(want), i
        assert {t.timestamp.ToNanoseconds() for t in m[7].texts} <= {m[1] - LAG}


def test_ground_truth_is_drawn_green_beside_the_estimate(ros2_written):
    _, _, written, _, gt, _, msgs = ros2_written
    gt_tf = [m for m in msgs if m[0] == "/batchpose/ground_truth/tf"]
    assert [m[1] for m in gt_tf] == [g["stamp_ns"] for g in gt]
    for m, g in zip(gt_tf, gt, strict=True):
        tf = m[7]
        assert (tf.parent_frame_id, tf.child_frame_id) == (OPTICAL, "gt/box")
        np.testing.assert_allclose([tf.translation.x, tf.translation.y, tf.translation.z], g["t_m"])
        q = [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix().ravel(), g["R"], atol=1e-9)
    scene = [(m[0], m[1], m[7]) for m in msgs if m[0].startswith("/batchpose/ground_truth/scene/")]
    for i in range(N):
        shown = _shown(scene, T0 + i * DT)
        assert list(shown) == ([] if i == 4 else [("/batchpose/ground_truth/scene/box", "box")]), i
        for e in shown.values():
            model = e.models[0]
            assert e.frame_id == "gt/box" and model.override_color and model.color.g > 0.5 > model.color.a
    assert written.scene_topics == (
        "/batchpose/scene/box",
        "/batchpose/scene/can",
        "/batchpose/ground_truth/scene/box",
    )


def _assert_tf(tf_msgs: list[tuple], rows: list[dict], parent: str, stamp) -> None:
    """``/tf`` holds, at each image with ok poses, one TFMessage of exactly those poses."""
    ok = [r for r in rows if r["status"] == "ok"]
    times = sorted({r["stamp_ns"] for r in ok})
    assert [m[1] for m in tf_msgs] == times
    for m in tf_msgs:
        want = {f"batchpose/{r['obj_name']}": r for r in ok if r["stamp_ns"] == m[1]}
        got = {tr.child_frame_id: tr for tr in m[7].transforms}
        assert got.keys() == want.keys()
        for child, tr in got.items():
            assert tr.header.frame_id == parent and stamp(tr.header.stamp) == m[1] - LAG
            t, q = tr.transform.translation, tr.transform.rotation
            np.testing.assert_allclose([t.x, t.y, t.z], want[child]["t_m"])
            R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            np.testing.assert_allclose(R.ravel(), want[child]["R"], atol=1e-9)


def test_ros2_log_gets_the_poses_on_tf(ros2_written):
    _, out, written, rows, _, _, msgs = ros2_written
    tf_msgs = [m for m in msgs if m[0] == "/tf"]
    assert {(m[4], m[5]) for m in tf_msgs} == {("tf2_msgs/msg/TFMessage", "cdr")}
    _assert_tf(tf_msgs, rows, OPTICAL, lambda s: s.sec * 1_000_000_000 + s.nanosec)
    assert written.n_ros_tf == len(tf_msgs) == N  # every image finds one object or the other
    no_tf = out.with_name("no_tf.mcap")
    write_poses_mcap(no_tf, rows, {}, input_mcap=out.with_name("in.mcap"), ros_tf=False)
    assert "/tf" not in {m[0] for m in _messages(no_tf)}


def test_ros1_log_gets_the_poses_on_tf(tmp_path):
    rng = np.random.default_rng(3)
    stamps = [T0 + i * DT for i in range(3)]
    records = []
    for t in stamps:
        records.append(ros1_record("/cam/camera_info", ros1_camera_info(t - LAG), t))
        records.append(ros1_record("/cam/image_raw", ros1_image(t - LAG, _img(rng), "bgr8"), t))
    ros1_log(tmp_path / "ros1.mcap", records)
    rows = plan_rows(stamps, {"box": ["ok", "hidden", "ok"]})
    out = tmp_path / "poses.mcap"
    write_poses_mcap(out, rows, {}, input_mcap=tmp_path / "ros1.mcap")
    tf_msgs = [m for m in _messages(out, [Ros1Decoders()]) if m[0] == "/tf"]
    assert {(m[4], m[5]) for m in tf_msgs} == {("tf2_msgs/TFMessage", "ros1")}
    _assert_tf(tf_msgs, rows, "cam", lambda s: s.to_nsec())


def _model(name: str, extents) -> ObjectModel:
    mesh = trimesh.creation.box(extents=extents)
    return ObjectModel(name, Path(f"{name}.obj"), mesh, float(np.linalg.norm(extents)), name)


def test_the_layout_names_the_logs_own_topics_and_frame(ros2_written, tmp_path, caplog):
    log_path, _, _, rows, gt, _, _ = ros2_written
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    pd.DataFrame(rows).to_parquet(run_dir / "poses.parquet")
    models = {"box": _model("box", (0.1, 0.2, 0.05)), "can": _model("can", (0.07, 0.07, 0.1))}
    inputs = export_mcap.ExportInputs(
        run_dir / "poses.parquet", models, {"format": "mcap", "path": str(log_path)}, McapFrameSource(log_path)
    )
    with caplog.at_level(logging.INFO, logger="batchpose"):
        assert export_mcap.main(None, inputs, run_dir) == run_dir / "poses.mcap"
    path = run_dir / "foxglove_layout.json"
    assert f"Foxglove layout: {path}" in caplog.text
    layout = json.loads(path.read_text())
    image, three_d = layout["configById"]["Image!batchpose"], layout["configById"]["3D!batchpose"]
    assert (image["imageMode"]["imageTopic"], image["imageMode"]["calibrationTopic"]) == (IMAGE, INFO)
    assert three_d["followTf"] == OPTICAL
    assert three_d["topics"][IMAGE] == {"visible": True, "cameraInfoTopic": INFO, "distance": 1}
    assert three_d["topics"][INFO]["visible"]
    scenes = ["/batchpose/scene/box", "/batchpose/scene/can"]  # this run has no ground truth
    for panel in (image, three_d):
        assert sorted(t for t in panel["topics"] if "scene" in t) == scenes
        assert all(panel["topics"][t] == {"visible": True} for t in scenes)
    assert not any("/camera/image" in json.dumps(p) for p in (image, three_d))
    # Asked again with the same options it is up to date; without /tf it is written again, without it.
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="batchpose"):
        export_mcap.main(None, inputs, run_dir)
    assert "Skipping MCAP export" in caplog.text and f"Foxglove layout: {path}" in caplog.text
    assert "/tf" in {m[0] for m in _messages(run_dir / "poses.mcap")}
    export_mcap.main(None, export_mcap.ExportInputs(*list(inputs.__dict__.values())[:4], ros_tf=False), run_dir)
    assert "/tf" not in {m[0] for m in _messages(run_dir / "poses.mcap")}


def test_folder_frames_get_ground_truth_with_the_objects_ids(tmp_path):
    # The demo frames: the gelatin box is in the first scene, the cracker box in the second.
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    source = open_frames({"format": "ycbv", "root": str(DEMO / "ycbv")}, DEMO)
    names = ["003_cracker_box", "009_gelatin_box"]
    ingest.main(None, ingest.IngestInputs(source, names), run_dir)
    ids = {"003_cracker_box": 1, "009_gelatin_box": 2}  # the run's ids, not the data set's (2 and 8)
    (run_dir / "objects.json").write_text(json.dumps({n: {"obj_id": i} for n, i in ids.items()}))
    gt = pd.read_parquet(run_dir / "gt.parquet").merge(pd.read_parquet(run_dir / "frames.parquet"), on="frame_id")
    poses = gt.assign(status="ok", reason="", confidence=0.9, n_inliers=30, inliers_px=[[]] * len(gt))
    poses.to_parquet(run_dir / "poses.parquet")
    models = {n: _model(n, (0.1, 0.15, 0.05)) for n in names}
    inputs = export_mcap.ExportInputs(run_dir / "poses.parquet", models, {"format": "ycbv"}, source)
    export_mcap.main(None, inputs, run_dir)
    msgs = _messages(run_dir / "poses.mcap", [ProtobufDecoders()])
    gt_msgs = [json.loads(m[6]) for m in msgs if m[0] == "/ground_truth/poses"]
    assert len(gt_msgs) == 5
    assert {(o["obj_name"], o["obj_id"]) for g in gt_msgs for o in g["objects"] if o["obj_name"] in ids} == set(
        ids.items()
    )
    stamps = sorted(set(gt["stamp_ns"]))
    for topic_prefix in ("/batchpose/scene/", "/batchpose/ground_truth/scene/"):
        scene = [(m[0], m[1], m[7]) for m in msgs if m[0].startswith(topic_prefix)]
        seen = [sorted(k[1] for k in _shown(scene, t)) for t in stamps]
        assert seen == [["009_gelatin_box"]] * 3 + [["003_cracker_box"]] * 2  # one scene's meshes leave with it
    gt_tf = [m[7] for m in msgs if m[0] == "/batchpose/ground_truth/tf"]
    assert [(tf.parent_frame_id, tf.child_frame_id) for tf in gt_tf] == [("camera", f"gt/{n}") for n in gt["obj_name"]]
    layout = json.loads((run_dir / "foxglove_layout.json").read_text())["configById"]
    assert layout["Image!batchpose"]["imageMode"]["imageTopic"] == "/camera/image"
    assert layout["3D!batchpose"]["followTf"] == "camera"
    assert "/batchpose/ground_truth/scene/003_cracker_box" in layout["3D!batchpose"]["topics"]


def _with_own_tf(src: Path, dst: Path, name: str, definition: str, data: bytes) -> Path:
    """``src`` with a first message on ``/tf`` of the type ``name`` (ros2msg ``definition``, cdr bytes)."""
    with open(src, "rb") as f, open(dst, "wb") as g:
        w = Writer(g)
        w.start(profile="ros2", library="test")
        tf = w.register_channel("/tf", "cdr", w.register_schema(name, "ros2msg", definition.encode()))
        w.add_message(tf, log_time=T0 - 5, data=data, publish_time=T0 - 5)
        ids: dict[str, int] = {}
        for s, ch, m in make_reader(f).iter_messages():
            if ch.topic not in ids:
                ids[ch.topic] = w.register_channel(ch.topic, "cdr", w.register_schema(s.name, s.encoding, s.data))
            w.add_message(ids[ch.topic], log_time=m.log_time, data=m.data, publish_time=m.publish_time)
        w.finish()
    return dst


def test_a_log_with_its_own_tf_gets_the_poses_on_that_channel(tmp_path, caplog):
    stamps = [T0 + i * DT for i in range(2)]
    rows = plan_rows(stamps, {"box": ["ok", "ok"]})
    plain = ros2_log(tmp_path / "plain.mcap", n=2)
    transform = {"translation": {"x": 0.0, "y": 0.0, "z": 1.0}, "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}
    robot_tf = {"transforms": [{"header": _header(T0, "base_link"), "child_frame_id": OPTICAL, "transform": transform}]}
    tf_type = "tf2_msgs/msg/TFMessage"
    data = serialize_dynamic(tf_type, ROS2_TF)[tf_type](robot_tf)
    # The robot's own tf2 /tf: the poses go on that channel, after its message.
    out = tmp_path / "poses.mcap"
    write_poses_mcap(out, rows, {}, input_mcap=_with_own_tf(plain, tmp_path / "tf.mcap", tf_type, ROS2_TF, data))
    with open(out, "rb") as f:
        assert [c.topic for c in make_reader(f).get_summary().channels.values()].count("/tf") == 1
    tf_msgs = [m for m in _messages(out, [Ros2Decoders()]) if m[0] == "/tf"]
    assert [m[1] for m in tf_msgs] == [T0 - 5, *stamps] and tf_msgs[0][6] == data
    assert tf_msgs[0][7].transforms[0].header.frame_id == "base_link"
    _assert_tf(tf_msgs[1:], rows, OPTICAL, lambda s: s.sec * 1_000_000_000 + s.nanosec)
    # A /tf of another type is left as it was, with a warning.
    other = _with_own_tf(plain, tmp_path / "other.mcap", "my_msgs/msg/Tf", "string data\n", bytes(12))
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        write_poses_mcap(out, rows, {}, input_mcap=other)
    assert [m[1] for m in _messages(out) if m[0] == "/tf"] == [T0 - 5]
    assert "/tf is my_msgs/msg/Tf (cdr) in the input log, not tf2_msgs/msg/TFMessage" in caplog.text

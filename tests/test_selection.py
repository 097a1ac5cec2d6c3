"""Which frames a run uses: the manifest's ``frames:`` keys every / frame_ids / from_s / to_s
(batchpose.io.sources.Selection) on small folder data sets and logs, and through ``batchpose run``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from batchpose.core.frames import FrameSource
from batchpose.errors import ConfigError, DataError
from batchpose.io.mcap_read import McapFrameSource
from batchpose.io.sources import SelectedFrames, Selection, open_frames
from tests.test_datasets import make_ycbv
from tests.test_mcap_io import DT, T0, Log, _calib, _cimg, _enc, _img

ROOT = Path(__file__).resolve().parents[1]


def _log(path, n: int = 6, summary: bool = True, lead_s: float = 1.0) -> list[int]:
    """A log whose first message (IMU) comes ``lead_s`` before the first of ``n`` images, DT apart;
    returns the images' log times."""
    rng = np.random.default_rng(0)
    log_ = Log(path, summary=summary)
    log_.json("/imu", {"a": 1}, T0)
    times = []
    for i in range(n):
        t = T0 + int(lead_s * 1e9) + i * DT
        log_.proto("/cam/calibration", _calib(t), t)
        log_.proto("/cam/image", _cimg(t, _enc(_img(rng), ".jpg")), t, seq=i)
        times.append(t)
    log_.close()
    return times


def test_every_keeps_every_nth_frame_and_tells_tracking_the_step(tmp_path):
    make_ycbv(tmp_path)
    all_ids = [f.frame_id for f in open_frames({"format": "ycbv", "root": "."}, tmp_path)]
    src = open_frames({"format": "ycbv", "root": ".", "every": 2}, tmp_path)
    assert isinstance(src, SelectedFrames)
    frames = list(src)
    assert [f.frame_id for f in frames] == all_ids[::2] == ["0001/000001", "data_syn/000007"]
    assert src.count() == 2 and [f.im_step for f in frames] == [2, 2]
    assert src.describe().endswith("; every 2nd frame")
    assert src.obj_id("003_cracker_box") == 2
    # no selection: the plain source, one step
    plain = open_frames({"format": "ycbv", "root": "."}, tmp_path)
    assert not isinstance(plain, SelectedFrames) and {f.im_step for f in plain} == {1}


def test_frame_ids_keep_the_listed_frames_in_source_order(tmp_path):
    make_ycbv(tmp_path)
    spec = {"format": "ycbv", "root": ".", "frame_ids": ["data_syn/000007", "0001/000001"]}
    src = open_frames(spec, tmp_path)
    assert [f.frame_id for f in src] == ["0001/000001", "data_syn/000007"]
    assert src.count() == 2
    bad = open_frames({**spec, "frame_ids": ["0001/000001", "0001/000099"]}, tmp_path)
    with pytest.raises(DataError, match=r"frames.frame_ids: 1 listed frame\(s\) not in ycbv .* e.g. '0001/000099'"):
        list(bad)


@pytest.mark.parametrize("summary", [True, False])
def test_a_time_window_counts_from_the_logs_first_message(tmp_path, summary):
    path = tmp_path / "log.mcap"
    times = _log(path, summary=summary)
    assert McapFrameSource(path).start_ns == T0  # the IMU message, 1 s before the first image
    # images at 1.00, 1.05, 1.10, 1.15, 1.20, 1.25 s after the start
    src = open_frames({"format": "mcap", "path": "log.mcap", "from_s": 1.04, "to_s": 1.2}, tmp_path)
    assert [f.stamp_ns for f in src] == times[1:4]
    assert src.count() == 3
    both = open_frames({"format": "mcap", "path": "log.mcap", "from_s": 1.04, "every": 2}, tmp_path)
    assert [f.stamp_ns for f in both] == [times[1], times[3], times[5]]
    assert "every 2nd frame, from 1.04 s" in both.describe()
    # An indexed log comes in time order: reading stops at the first image past the window.
    inner, pulled = McapFrameSource(path), []

    class Counting(FrameSource):
        start_ns, time_ordered = inner.start_ns, inner.time_ordered

        def __iter__(self):
            for f in inner:
                pulled.append(f.stamp_ns)
                yield f

        def count(self):
            return inner.count()

        def describe(self):
            return "counting"

    assert [f.stamp_ns for f in SelectedFrames(Counting(), Selection(to_s=1.12))] == times[:3]
    assert pulled == (times[:4] if summary else times)


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        ({"every": 0}, "frames.every: expected a whole number >= 1, got 0"),
        ({"every": 2.5}, "frames.every: expected a whole number >= 1, got 2.5"),
        ({"every": True}, "frames.every: expected a whole number >= 1, got True"),
        ({"frame_ids": "0001/000001"}, "frames.frame_ids: expected a list of frame ids"),
        ({"from_s": 1.0}, r"frames.from_s: only for format mcap \(a ycbv folder has no capture times"),
        ({"every": 2, "evrey": 3}, "frames.evrey: unknown key for format ycbv"),
    ],
)
def test_bad_selection_keys_are_one_line_config_errors(tmp_path, extra, match):
    make_ycbv(tmp_path)
    with pytest.raises(ConfigError, match=match):
        open_frames({"format": "ycbv", "root": ".", **extra}, tmp_path)


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        ({"from_s": -1}, r"frames.from_s: expected seconds after the log's start \(a number >= 0\), got -1"),
        ({"to_s": "10s"}, "frames.to_s: expected seconds after the log's start .* got '10s'"),
        ({"from_s": 5, "to_s": 5}, r"frames.to_s \(5\) must be after frames.from_s \(5\)"),
    ],
)
def test_bad_time_windows(tmp_path, extra, match):
    _log(tmp_path / "log.mcap")
    with pytest.raises(ConfigError, match=match):
        open_frames({"format": "mcap", "path": "log.mcap", **extra}, tmp_path)


def test_a_run_over_every_other_frame_of_a_log_keeps_the_whole_log(tmp_path, cache_dir):
    """`batchpose run` with `every: 2` on the demo frames converted to a log: poses for frames 1, 3, 5
    only, the output log still holds all five images, and a rerun with the selection widened estimates
    only the frames it adds."""
    log_path = tmp_path / "demo.mcap"
    subprocess.run(
        [sys.executable, "-m", "batchpose", "convert", "--format", "ycbv", str(ROOT / "demo_data/ycbv"), str(log_path)],
        check=True,
        capture_output=True,
    )
    frames = {"format": "mcap", "path": str(log_path), "every": 2}
    manifest = tmp_path / "m.yaml"

    def run(frames_spec):
        manifest.write_text(
            yaml.safe_dump(
                {
                    "name": "sel",
                    "frames": frames_spec,
                    "models": {"root": str(ROOT / "demo_data/models"), "mesh": "{name}/textured.obj"},
                    "objects": ["003_cracker_box", "009_gelatin_box"],
                }
            )
        )
        cmd = [sys.executable, "-m", "batchpose", "run", str(ROOT / "pipelines/gnc_pose.yaml"), "--manifest"]
        r = subprocess.run(
            [*cmd, str(manifest), "--out", str(tmp_path / "out"), "--cache", str(cache_dir), "--jobs", "1"],
            capture_output=True,
            text=True,
            check=False,
        )
        assert r.returncode == 0, r.stderr
        return r.stderr, pd.read_parquet(tmp_path / "out" / "poses.parquet")

    everything = [f.frame_id for f in McapFrameSource(log_path)]
    err, poses = run(frames)
    assert sorted(set(poses["frame_id"])) == sorted(everything[::2])
    assert "every 2nd frame" in err and "(5 images, " in err
    assert (poses["status"] == "ok").all()
    err, wider = run({**frames, "every": 1})
    assert sorted(set(wider["frame_id"])) == sorted(everything)
    assert f"Resuming: {len(poses)} (frame, object) pairs already estimated" in err


def test_a_window_past_the_end_of_the_log_is_one_line_exit_2(tmp_path):
    _log(tmp_path / "log.mcap")
    manifest = tmp_path / "m.yaml"
    manifest.write_text(
        yaml.safe_dump(
            {
                "name": "late",
                "frames": {"format": "mcap", "path": "log.mcap", "from_s": 60},
                "models": {"root": str(ROOT / "demo_data/models"), "mesh": "{name}/textured.obj"},
                "objects": ["003_cracker_box"],
                "targets": "all",
            }
        )
    )
    cmd = [sys.executable, "-m", "batchpose", "run", str(ROOT / "pipelines/gnc_pose.yaml"), "--manifest"]
    r = subprocess.run(
        [*cmd, str(manifest), "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache")],
        capture_output=True,
        text=True,
        check=False,
    )
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("batchpose: error:")]
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert errors == [
        f"batchpose: error: {manifest}: none of the data set's frames is chosen (from 60 s; its images span "
        "1-1.25 s of the log)"
    ]

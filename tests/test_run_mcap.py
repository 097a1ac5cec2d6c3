"""`batchpose run` on MCAP input: the full job on a converted log, and bad logs from the CLI (issue 3/4)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from mcap.reader import make_reader

from batchpose import convert, run
from tests.conftest import ROOT
from tests.test_mcap_io import T0, Log, _calib, _enc, _simple_log

PIPELINE = ROOT / "pipelines" / "gnc_pose.yaml"
MODELS = ROOT / "demo_data" / "models"


def _manifest(tmp_path, log_path) -> str:
    m = tmp_path / "m.yaml"
    m.write_text(
        f"name: log\nframes: {{format: mcap, path: {log_path}}}\n"
        f"models: {{root: {MODELS}, mesh: '{{name}}/textured.obj', points: '{{name}}/points.xyz'}}\n"
        "objects: [009_gelatin_box]\ntargets: annotations\n"
    )
    return str(m)


@pytest.mark.slow
def test_run_on_converted_log_keeps_input_and_adds_poses(tmp_path, cache_dir):
    log_path = convert.main(ROOT / "demo_data" / "ycbv", tmp_path / "demo.mcap", fmt="ycbv")
    out = run.main(PIPELINE, _manifest(tmp_path, log_path), tmp_path / "run", cache_dir=cache_dir, jobs=1)
    with open(log_path, "rb") as f:
        inp = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages()]
    with open(out / "poses.mcap", "rb") as f:
        outp = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f, validate_crcs=True).iter_messages()]
    assert set(inp) <= set(outp)
    topics = {t for t, _, _ in outp}
    assert {"/camera/image", "/camera/calibration"} <= topics
    assert len(topics) > 3  # pose topics were added
    frames = pd.read_csv(out / "report" / "frames.csv")
    gel = frames[frames["obj_name"] == "009_gelatin_box"]
    assert len(gel) == 3 and (gel["add_m"] < 0.1 * gel["diameter_m"]).all()


def _bad_logs(tmp_path):
    not_mcap = tmp_path / "photo.mcap"
    not_mcap.write_bytes(_enc(np.zeros((4, 4, 3), np.uint8)))
    cut = tmp_path / "cut.mcap"
    _simple_log(cut)
    cut.write_bytes(cut.read_bytes()[:200])
    crc = tmp_path / "crc.mcap"
    datas = _simple_log(crc)
    raw = bytearray(crc.read_bytes())
    raw[raw.find(datas[1]) + 100] ^= 0xFF
    crc.write_bytes(bytes(raw))
    imu = tmp_path / "imu.mcap"
    log_ = Log(imu)
    log_.json("/imu", {"a": 1}, T0)
    log_.proto("/cam/calibration", _calib(T0), T0)
    log_.close()
    return [
        (not_mcap, "photo.mcap: not an MCAP file"),
        (cut, "cut.mcap: truncated MCAP"),
        (crc, "crc.mcap: CRC mismatch"),
        (imu, "imu.mcap: no image topic"),
    ]


def test_bad_logs_from_the_cli_are_one_line_exit_2(tmp_path):
    for path, expect in _bad_logs(tmp_path):
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "batchpose",
                "run",
                str(PIPELINE),
                "--manifest",
                _manifest(tmp_path, path),
                "--out",
                str(tmp_path / f"out-{path.stem}"),
                "--cache",
                str(tmp_path / "cache"),
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        errors = [ln for ln in r.stderr.splitlines() if ln.startswith("batchpose: error:")]
        assert r.returncode == 2, r.stderr
        assert len(errors) == 1 and "Traceback" not in r.stderr, r.stderr
        assert expect in errors[0], errors[0]

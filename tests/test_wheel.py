"""``pip install batchpose``: a wheel built from this checkout holds the bundled pipelines and the Foxglove layout
as real files, and, installed into a fresh environment with no checkout on its path, runs the demo with the
default pipeline from a folder outside the repository.

The fresh environment borrows the dependencies of the running one (a ``.pth`` file naming its site-packages),
not its batchpose: a ``.pth`` line only adds a folder to ``sys.path``, so the editable install's own ``.pth``
in that folder is never run."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pandas as pd
import pytest
import yaml

from batchpose.config import load_estimator_config, load_yaml, to_dict
from tests.conftest import ROOT

pytestmark = pytest.mark.slow

SOURCES = ["pyproject.toml", "README.md", "batchpose", "pipelines", "foxglove"]


def _setuptools_builds_here() -> bool:
    """True when this environment's setuptools can build the wheel itself (pyproject.toml needs >= 77)."""
    try:
        import setuptools
    except ImportError:
        return False
    return int(setuptools.__version__.split(".")[0]) >= 77


def _run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
    r = subprocess.run(cmd, capture_output=True, text=True, **kwargs)
    assert r.returncode == 0, f"{' '.join(map(str, cmd))}\n{r.stdout}\n{r.stderr}"
    return r


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A wheel built from a copy of the checkout's sources (symlinks kept as symlinks), so the build writes
    nothing into the checkout."""
    src = tmp_path_factory.mktemp("src")
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(path, src / name)
    dist = tmp_path_factory.mktemp("dist")
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(src)]
    # Without setuptools >= 77 here, pip fetches it for an isolated build.
    _run(cmd + (["--no-build-isolation"] if _setuptools_builds_here() else []))
    (whl,) = dist.glob("batchpose-*.whl")
    return whl


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory) -> Path:
    """A fresh environment with the wheel installed, borrowing this environment's dependencies."""
    env = tmp_path_factory.mktemp("venv")
    _run([sys.executable, "-m", "venv", "--without-pip", str(env)])
    # Installed before the dependencies are made visible: pip then sees no batchpose there to replace.
    _run([sys.executable, "-m", "pip", "--python", str(env / "bin" / "python"), "install", "-q", "--no-deps",
          "--no-index", str(wheel)])  # fmt: skip
    code = "import sysconfig; print(sysconfig.get_paths()['purelib'])"
    purelib = Path(_run([str(env / "bin" / "python"), "-c", code]).stdout.strip())
    (purelib / "borrowed_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return env


def _clean_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.setdefault("PYOPENGL_PLATFORM", "osmesa")
    return env


def test_the_wheel_holds_the_pipelines_and_the_layout_as_real_files(wheel):
    with zipfile.ZipFile(wheel) as z:
        infos = {i.filename: i for i in z.infolist()}
        bundled = {n for n in infos if n.startswith("batchpose/pipelines/")}
        assert bundled == {f"batchpose/pipelines/{p.name}" for p in ROOT.glob("pipelines/*.yaml")}
        for name in [*bundled, "batchpose/foxglove/layout.json"]:
            assert not stat.S_ISLNK(infos[name].external_attr >> 16), f"{name} is a symlink in the wheel"
            assert z.read(name) == (ROOT / name.removeprefix("batchpose/")).read_bytes(), name


@pytest.fixture(scope="module")
def installed_run(venv, cache_dir, tmp_path_factory) -> Path:
    """``batchpose run`` of the installed wheel on the demo's first frame, from a folder outside the checkout."""
    outside = tmp_path_factory.mktemp("elsewhere")
    out = outside / "run"
    cmd = [str(venv / "bin" / "batchpose"), "run", "--manifest", str(ROOT / "data_manifest" / "demo.yaml"),
           "--out", str(out), "--limit", "1", "--jobs", "1", "--cache", str(cache_dir)]  # fmt: skip
    _run(cmd, cwd=outside, env=_clean_env(), timeout=600)
    return out


def test_the_installed_package_is_the_wheels_and_finds_its_data(venv, tmp_path):
    code = (
        "import json, batchpose; from batchpose.config import pipelines as p; "
        "print(json.dumps([batchpose.__file__, str(p.resolve(p.DEFAULT)), str(p.layout_template())]))"
    )
    paths = json.loads(_run([str(venv / "bin" / "python"), "-c", code], cwd=tmp_path, env=_clean_env()).stdout)
    for path in paths:
        assert Path(path).resolve().is_relative_to(venv.resolve()), paths
    assert Path(paths[1]).read_bytes() == (ROOT / "pipelines" / "gnc_pose.yaml").read_bytes()


def test_the_installed_command_runs_the_demo_with_the_default_pipeline(installed_run):
    poses = pd.read_csv(installed_run / "poses.csv")
    assert len(poses) >= 1 and set(poses.columns) >= {"scene_id", "im_id", "obj_id", "R", "t"}
    status = pd.read_parquet(installed_run / "poses.parquet")["status"]
    assert (status == "ok").sum() == len(poses) >= 1
    saved = yaml.safe_load((installed_run / "config.yaml").read_text())["pipeline"]
    assert saved == to_dict(load_estimator_config(load_yaml(ROOT / "pipelines" / "gnc_pose.yaml")))

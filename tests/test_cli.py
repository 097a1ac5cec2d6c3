"""The command line's manners: -v anywhere, examples in every --help, bundled pipelines by name, and --set
mistakes blamed on --set with the nearest key. None of these runs the pipeline (each fails or ends before)."""

from __future__ import annotations

import argparse
import logging
import subprocess
import sys
from pathlib import Path

import pytest

from batchpose import cli
from batchpose.config import ConfigError, apply_overrides, pipelines
from tests.conftest import ROOT

DEMO = ROOT / "data_manifest" / "demo.yaml"
COMMANDS = ["run", "inspect", "init", "convert", "report", "compare", "score", "pipelines"]


def _cli(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "batchpose", *args], capture_output=True, text=True, cwd=cwd)


def _one_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("batchpose: error: "), stderr
    return lines[0].removeprefix("batchpose: error: ")


def _exit_2(capsys, *args: str) -> str:
    """cli.main in this process: exit code 2 and the one error line."""
    assert cli.main(list(args)) == 2
    return _one_line(capsys.readouterr().err)


@pytest.fixture()
def quiet_logger():
    """cli.main adds a handler and sets the level of the "batchpose" logger: put both back afterwards."""
    log = logging.getLogger("batchpose")
    handlers, level, propagate = list(log.handlers), log.level, log.propagate
    yield log
    log.handlers[:], log.propagate = handlers, propagate
    log.setLevel(level)


def test_verbose_is_accepted_before_and_after_the_command(quiet_logger, capsys):
    parser = cli.build_parser()
    assert parser.parse_args(["pipelines"]).verbose is False
    assert parser.parse_args(["-v", "pipelines"]).verbose is True
    assert parser.parse_args(["pipelines", "-v"]).verbose is True
    assert parser.parse_args(["run", "--manifest", "m.yaml", "--out", "o", "--verbose"]).verbose is True
    assert cli.main(["pipelines", "-v"]) == 0
    assert quiet_logger.level == logging.DEBUG  # the -v after the command reached the logger
    assert "gnc_pose" in capsys.readouterr().out


def test_every_command_has_examples_in_its_help(capsys):
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert sorted(sub.choices) == sorted(COMMANDS)
    for name in COMMANDS:
        with pytest.raises(SystemExit) as e:
            cli.main([name, "--help"])
        assert e.value.code == 0
        text = capsys.readouterr().out
        examples = text[text.index("examples:") :]
        assert f"  batchpose {name}" in examples, (name, text)


def test_an_unknown_set_key_is_blamed_on_set_with_the_nearest_key(tmp_path):
    out = tmp_path / "run"
    # -v after the command, and PIPELINE and --pipeline naming the same file, are accepted on the way.
    r = _cli("run", "pipelines/gnc_pose.yaml", "--pipeline", "gnc_pose", "--manifest", str(DEMO), "--out", str(out),
             "--set", "gnc.kapa=3", "-v")  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert _one_line(r.stderr) == "--set gnc.kapa=3: unknown key gnc.kapa; did you mean gnc.kappa?"
    assert not out.exists()


@pytest.mark.parametrize(
    "item, message",
    [
        ("kappa=3", "--set kappa=3: unknown key kappa; did you mean gnc.kappa?"),
        ("gcn.kappa=3", "--set gcn.kappa=3: unknown key gcn.kappa; did you mean gnc.kappa?"),
        ("gnc.kappa=abc", "--set gnc.kappa=abc: expected a number, got 'abc'"),
        ("gnc.kappa=-1", "--set gnc.kappa=-1: gnc.kappa must be positive, got -1.0"),
        ("gnc.kappa.x=1", "--set gnc.kappa.x=1: gnc.kappa is a value, not a section (e.g. --set gnc.kappa=...)"),
        ("method=gnc", "--set method=gnc: method = 'gnc', expected one of gnc_pose, tp_ub"),
    ],
)
def test_set_mistakes_name_set(item, message):
    with pytest.raises(ConfigError) as e:
        apply_overrides({}, [item])
    assert str(e.value) == message


def test_an_unknown_pipeline_name_gets_the_nearest_and_the_list(tmp_path, quiet_logger, capsys):
    msg = _exit_2(capsys, "run", "--pipeline", "nosuch", "--manifest", str(DEMO), "--out", str(tmp_path / "o"))
    assert msg.startswith("pipeline 'nosuch': no bundled pipeline of that name; did you mean ")
    assert all(name in msg for name in ("gnc_pose", "fast", "paper", "rgbd"))
    with pytest.raises(ConfigError, match="did you mean gnc_pose\\?"):
        pipelines.resolve("gnc_pos")
    with pytest.raises(ConfigError, match="nope/x.yaml: file not found"):
        pipelines.resolve("nope/x.yaml")


def test_positional_and_option_naming_different_pipelines_is_an_error(tmp_path, quiet_logger, capsys):
    fast = str(ROOT / "pipelines" / "fast.yaml")
    msg = _exit_2(capsys, "run", fast, "--pipeline", "gnc_pose", "--manifest", str(DEMO), "--out", str(tmp_path))
    assert msg == f"run: PIPELINE {fast} and --pipeline gnc_pose are different pipelines; give one of them"


def test_pipelines_lists_every_bundled_yaml_with_its_first_comment_line(quiet_logger, capsys):
    assert cli.main(["pipelines"]) == 0
    lines = capsys.readouterr().out.splitlines()
    yamls = sorted(ROOT.glob("pipelines/*.yaml"))
    assert len(yamls) >= 8
    for path in yamls:
        first = path.read_text().splitlines()[0]
        assert first.startswith("# "), f"{path.name} opens with no one-line description"
        row = next(ln for ln in lines if ln.split()[:1] == [path.stem])
        assert row.endswith(first.removeprefix("# ")), row
    assert any(ln.split()[:2] == ["gnc_pose", "(default)"] for ln in lines)


def test_resolve_by_name_and_by_path_agree():
    by_name = pipelines.resolve("gnc_pose")
    assert by_name.is_absolute() and by_name.resolve() == (ROOT / "pipelines" / "gnc_pose.yaml").resolve()
    assert pipelines.resolve(ROOT / "pipelines" / "gnc_pose.yaml").resolve() == by_name.resolve()
    assert pipelines.resolve("gnc_pose.yaml") == by_name  # no such file here: the bundled one
    assert pipelines.resolve(pipelines.DEFAULT) == by_name
    assert set(pipelines.available()) == {p.stem for p in ROOT.glob("pipelines/*.yaml")}
    assert pipelines.layout_template().read_bytes() == (ROOT / "foxglove" / "layout.json").read_bytes()

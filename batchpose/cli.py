"""Command-line interface: ``batchpose run | inspect | init | convert | report | compare | score | pipelines``.

Any :class:`~batchpose.errors.BatchposeError`, or a file the user named that cannot be read or written, is
printed as one line on stderr and exits with code 2; any other exception (a bug) as one line with code 1
(the traceback with ``-v``).
"""

from __future__ import annotations

import argparse
import errno
import logging
import shutil
import signal
import sys
import threading
from pathlib import Path

from batchpose.errors import BatchposeError

log = logging.getLogger("batchpose")


def _cmd_convert(args: argparse.Namespace) -> None:
    from batchpose import convert

    out = convert.main(Path(args.src), Path(args.out), fmt=args.format, overwrite=args.overwrite)
    print(f"wrote {out}")


def _pipeline_path(args: argparse.Namespace) -> Path:
    """The pipeline YAML of ``run``: ``--pipeline NAME|PATH``, or the positional ``PIPELINE`` of older scripts,
    or the default; both given must name the same file."""
    from batchpose.config import pipelines

    given = [v for v in (args.pipeline_file, args.pipeline) if v]
    paths = [pipelines.resolve(v) for v in given] or [pipelines.resolve(pipelines.DEFAULT)]
    if len(paths) == 2 and paths[0].resolve() != paths[1].resolve():
        raise BatchposeError(
            f"run: PIPELINE {given[0]} and --pipeline {given[1]} are different pipelines; give one of them"
        )
    return paths[-1]


def _cmd_run(args: argparse.Namespace) -> None:
    from batchpose import run

    run.main(
        _pipeline_path(args),
        Path(args.manifest),
        Path(args.out),
        cache_dir=Path(args.cache) if args.cache else None,
        overrides=args.set or [],
        jobs=args.jobs,
        backend=args.backend,
        scheduler=args.scheduler,
        overwrite=args.overwrite,
        limit=args.limit,
        ros_tf=args.ros_tf,
    )


def _cmd_pipelines(args: argparse.Namespace) -> None:
    from batchpose.config import pipelines

    labels = {n: f"{n} (default)" if n == pipelines.DEFAULT else n for n in pipelines.available()}
    width = max(map(len, labels.values()))
    for name, text in pipelines.available().items():
        print(f"  {labels[name]:<{width}}  {text or '(no description)'}")
    print(f"\nbatchpose run --pipeline NAME ...; to make your own, copy one from {pipelines.pipelines_dir()}")


def _cmd_inspect(args: argparse.Namespace) -> None:
    from batchpose import inspect_log

    print(inspect_log.describe(Path(args.path)))


def _cmd_init(args: argparse.Namespace) -> None:
    from batchpose import init_manifest

    out = init_manifest.main(
        Path(args.log),
        Path(args.meshes),
        Path(args.out),
        overwrite=args.overwrite,
        image_topic=args.image_topic,
        calibration_topic=args.calibration_topic,
    )
    out = Path(out) if out else Path(args.out)
    print(f"wrote {out}")
    print(f"next: batchpose run --manifest {out} --out runs/{out.stem}")


def _cmd_report(args: argparse.Namespace) -> None:
    from batchpose.stages import report as report_stage

    out = report_stage.main(None, None, Path(args.run_dir), overwrite=True)
    print(f"report: {out}")


def _cmd_compare(args: argparse.Namespace) -> None:
    from batchpose.stages import report as report_stage

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise BatchposeError(f"compare --out {out}: is a file, not a directory")
    if out.is_dir() and any(out.iterdir()) and not (out / "compare.csv").is_file():
        raise BatchposeError(
            f"compare --out {out}: is not empty and holds no comparison (no compare.csv); give a new or empty directory"
        )
    out = report_stage.compare([Path(p) for p in args.run_dirs], out)
    print(f"compare: {out}")


def _cmd_score(args: argparse.Namespace) -> None:
    from batchpose.report import runs, scoring

    run = runs.load_run(Path(args.run_dir))
    if run.gt is None or run.gt.empty:
        raise BatchposeError(f"{args.run_dir}: the run has no ground truth (gt.parquet) to score against")
    points, diameters = run.model_points(sorted(run.objects))
    obj_names = {int(v["obj_id"]): k for k, v in run.objects.items()}
    _, summary = scoring.score_bop_csv(Path(args.csv), run.gt, points, diameters, obj_names, frames=run.frames, run=run)
    cols = ["obj_name", "n", "adds_auc", "add_auc", "adds_recall_01d", "add_recall_01d"]
    cols += [c for c in ("ar_vsd", "ar_mssd", "ar_mspd", "ar") if c in summary]  # BOP 2019 average recalls
    digits = {c: "{:.3f}" if c.startswith("ar") else "{:.1f}" for c in cols[2:]}
    print(summary[cols].to_string(index=False, formatters={c: f.format for c, f in digits.items()}))


def _examples(*lines: str) -> str:
    return "examples:\n" + "\n".join(f"  {line}" for line in lines)


def _subcommand(sub, common: argparse.ArgumentParser, name: str, examples: list[str], **kwargs):
    """A subcommand that takes ``-v`` too and ends its ``--help`` with examples."""
    return sub.add_parser(
        name,
        parents=[common],
        epilog=_examples(*examples),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        **kwargs,
    )


def _add_run(sub, common: argparse.ArgumentParser) -> None:
    r = _subcommand(
        sub,
        common,
        "run",
        [
            "batchpose run --manifest data_manifest/demo.yaml --out runs/demo",
            "batchpose run --pipeline fast --manifest my_log.yaml --out runs/my_log_fast --set gnc.kappa=3",
            "batchpose run --pipeline my_pipeline.yaml --manifest my_log.yaml --out runs/mine --jobs 4",
        ],
        help="run the pipeline: ingest -> templates -> estimate -> carry -> MCAP -> report",
        description="Run a pipeline over the frames of a data manifest. Finished stages and finished "
        "(frame, object) pairs are skipped on a rerun; a killed run resumes.",
    )
    r.add_argument(
        "pipeline_file",
        nargs="?",
        metavar="PIPELINE",
        help="pipeline YAML (older form of --pipeline; if both are given they must agree)",
    )
    r.add_argument(
        "--pipeline",
        metavar="NAME|PATH",
        help="a bundled pipeline by name (`batchpose pipelines` lists them) or a pipeline YAML (default gnc_pose)",
    )
    r.add_argument("--manifest", required=True, help="data manifest YAML, e.g. data_manifest/demo.yaml")
    r.add_argument("--out", required=True, help="run directory for all outputs")
    r.add_argument("--cache", help="cache of template libraries and loaded meshes (default ~/.cache/batchpose)")
    r.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a pipeline field, e.g. --set gnc.kappa=3 (repeatable)",
    )
    r.add_argument("--jobs", type=int, default=2, help="parallel workers (default 2)")
    r.add_argument(
        "--backend",
        choices=("loky", "dask"),
        default="loky",
        help="joblib backend: loky (local processes, default) or dask (a distributed cluster)",
    )
    r.add_argument("--scheduler", help="Dask scheduler address tcp://HOST:PORT (with --backend dask)")
    r.add_argument("--overwrite", action="store_true", help="recompute every stage, ignoring earlier results")
    r.add_argument("--limit", type=int, help="process only the first N frames")
    r.add_argument(
        "--no-ros-tf",
        dest="ros_tf",
        action="store_false",
        help="do not add the poses as tf2_msgs/TFMessage on /tf to poses.mcap (added by default for ROS logs)",
    )
    r.set_defaults(func=_cmd_run)


def _add_data_commands(sub, common: argparse.ArgumentParser) -> None:
    """``inspect``, ``init`` and ``convert``: from a recording to what ``run`` reads."""
    i = _subcommand(
        sub,
        common,
        "inspect",
        ["batchpose inspect my_log.mcap", "batchpose inspect my_images/"],
        help="describe a log: topics, image sizes, calibration, time span, the image topic batchpose reads",
    )
    i.add_argument("path", help="the log (MCAP) or image folder to describe")
    i.set_defaults(func=_cmd_inspect)

    n = _subcommand(
        sub,
        common,
        "init",
        ["batchpose init my_log.mcap --meshes meshes/ --out my_log.yaml"],
        help="write a commented data manifest for a log and a folder of meshes",
        description="Write a data manifest for LOG and the meshes in --meshes, with comments on what to edit "
        "(frames, objects, topics), and print the `batchpose run` that uses it.",
    )
    n.add_argument("log", help="the log (MCAP) or image folder the manifest reads")
    n.add_argument(
        "--meshes", required=True, help="folder of meshes (meshes/NAME.obj, .ply, .glb or NAME/textured.obj)"
    )
    n.add_argument("--out", required=True, help="manifest YAML to write (must not exist unless --overwrite)")
    n.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    n.add_argument("--image-topic", help="the log's image topic to read (default: the one `inspect` names)")
    n.add_argument("--calibration-topic", help="the log's camera-info topic (default: the one beside the images)")
    n.set_defaults(func=_cmd_init)

    c = _subcommand(
        sub,
        common,
        "convert",
        [
            "batchpose convert my_images/ my_log.mcap --format images",
            "batchpose convert YCB_Video_Dataset/ ycbv.mcap --format ycbv",
        ],
        help="write a folder data set (YCB-Video, BOP, images) as an MCAP log",
        description="Write a folder data set as MCAP: /camera/image (foxglove.CompressedImage, bytes "
        "copied, never re-encoded), /camera/calibration (foxglove.CameraCalibration) and, when present, "
        "/ground_truth/poses.",
    )
    c.add_argument("src", help="data set folder")
    c.add_argument("out", help="output .mcap file (must not exist unless --overwrite)")
    c.add_argument("--format", required=True, choices=("ycbv", "bop", "images"), help="layout of SRC")
    c.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    c.set_defaults(func=_cmd_convert)


def _add_result_commands(sub, common: argparse.ArgumentParser) -> None:
    """``report``, ``compare``, ``score`` and ``pipelines``."""
    rep = _subcommand(
        sub, common, "report", ["batchpose report runs/demo"], help="(re)build RUN_DIR/report from a finished run"
    )
    rep.add_argument("run_dir", help="a run directory written by `batchpose run`")
    rep.set_defaults(func=_cmd_report)

    cmp_ = _subcommand(
        sub,
        common,
        "compare",
        ["batchpose compare runs/demo runs/demo_fast --out runs/compare"],
        help="compare several runs side by side (table + curves)",
    )
    cmp_.add_argument("run_dirs", nargs="+", help="run directories")
    cmp_.add_argument("--out", required=True, help="output directory for the comparison page")
    cmp_.set_defaults(func=_cmd_compare)

    sc = _subcommand(
        sub,
        common,
        "score",
        ["batchpose score other_method.csv runs/demo"],
        help="score any BOP-format results CSV against a run's ground truth",
        description="Score a BOP results file (scene_id,im_id,obj_id,score,R,t,time; t in mm) against the "
        "ground truth, frames and model points of a run directory: ADD(-S) AUC and 0.1 d recall per object.",
    )
    sc.add_argument("csv", help="BOP-format results CSV")
    sc.add_argument("run_dir", help="run directory whose gt.parquet, frames.parquet and objects.json to use")
    sc.set_defaults(func=_cmd_score)

    pl = _subcommand(
        sub,
        common,
        "pipelines",
        ["batchpose pipelines", "batchpose run --pipeline fast --manifest my_log.yaml --out runs/my_log_fast"],
        help="list the bundled pipelines, one line each",
    )
    pl.set_defaults(func=_cmd_pipelines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="batchpose",
        description="Learning-free 6D pose (GNC-Pose) of textured objects in camera logs, on CPU, in batch.",
        epilog=_examples(
            "batchpose inspect my_log.mcap",
            "batchpose init my_log.mcap --meshes meshes/ --out my_log.yaml",
            "batchpose run --manifest my_log.yaml --out runs/my_log",
            "batchpose COMMAND --help",
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging (before or after the command)")
    p.add_argument(
        "--version", action=_Version, nargs=0, help="print batchpose's version and its libraries' (for bug reports)"
    )
    # -v after the command too; SUPPRESS keeps a -v given before it.
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help="debug logging")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_run(sub, common)
    _add_data_commands(sub, common)
    _add_result_commands(sub, common)
    return p


class _Version(argparse.Action):
    """``--version``: batchpose's version, then the versions a run records in its ``versions.json``."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        from batchpose import __version__  # noqa: PLC0415
        from batchpose.run_dir import versions  # noqa: PLC0415

        libs = ", ".join(f"{k} {v}" for k, v in versions().items() if k not in ("batchpose", "platform") and v)
        print(f"batchpose {__version__} ({libs})")
        parser.exit()


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a cancelled CI job): stops the run as Ctrl-C does, workers included."""


def _on_sigterm(signum, frame) -> None:
    raise Terminated()


def _disk_full(args: argparse.Namespace, e: OSError) -> str:
    """The one line for a full disk: which of the command's output folders has no room, and what to do.

    A write that fails for space rarely names its file, so the command's own output folders (``--out``,
    ``--cache``, ``report``'s run directory) are named, the fullest first.
    """
    named = []
    for flag in ("out", "cache", "run_dir"):
        value = getattr(args, flag, None)
        if flag == "cache" and value is None and getattr(args, "func", None) is _cmd_run:
            from batchpose.io.library import default_cache_dir  # noqa: PLC0415

            value = default_cache_dir()
        if value is None:
            continue
        path = Path(value)
        while not path.exists() and path != path.parent:
            path = path.parent
        try:
            free = shutil.disk_usage(path).free
        except OSError:
            continue
        positional = flag == "run_dir" or (flag == "out" and getattr(args, "func", None) is _cmd_convert)
        label = {"run_dir": "run dir", "out": "output"}[flag] if positional else f"--{flag}"
        named.append((free, f"{label} {value} ({free / 1e6:.0f} MB free now)"))
    where = f" writing {e.filename}" if e.filename else ""
    disks = "; ".join(n for _, n in sorted(named)) if named else "the output folders"
    return f"no space left on device{where}: {disks}. Free some space and rerun the same command: finished work is kept"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_sigterm)
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(message)s" if args.verbose else "%(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.DEBUG if args.verbose else logging.INFO)
    log.propagate = False
    try:
        args.func(args)
    except BatchposeError as e:
        print(f"batchpose: error: {e}", file=sys.stderr)
        return 2
    except Terminated:
        print("batchpose: terminated (SIGTERM); a rerun resumes", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("batchpose: interrupted", file=sys.stderr)
        return 130
    except OSError as e:  # a file or folder the user named that cannot be read or written
        if e.errno in (errno.ENOSPC, errno.EDQUOT) or "No space left on device" in str(e):
            print(f"batchpose: error: {_disk_full(args, e)}", file=sys.stderr)
            return 2
        where = f"{e.filename}: " if e.filename else ""
        print(f"batchpose: error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - a bug: one line (the traceback with -v), not a crash dump
        if args.verbose:
            log.exception("internal error")
        first = (str(e).splitlines() or [""])[0]
        print(
            f"batchpose: internal error: {type(e).__name__}: {first} (rerun with -v for the traceback and "
            "please report it)",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

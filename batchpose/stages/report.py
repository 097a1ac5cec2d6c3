"""Stage: score a finished run and write ``RUN/report/{summary.csv, frames.csv, index.html}``; and the
``batchpose compare`` folder (``compare.csv``, ``index.html``).

The only module that writes the report's files: loading is :mod:`batchpose.report.runs`, the tables
:mod:`batchpose.report.scoring`, the overlays :mod:`batchpose.report.overlays` and the pages
:mod:`batchpose.report.html` (run directory layout in :mod:`batchpose.report.runs`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import pandas as pd

from batchpose.config import EstimatorConfig
from batchpose.io.files import write_text_atomic
from batchpose.report import html, overlays, scoring
from batchpose.report.compare import compare_runs
from batchpose.report.runs import load_run
from batchpose.stages import up_to_date

log = logging.getLogger("batchpose")

#: The run's tables the report is made from: a report older than any of them is rebuilt.
INPUTS = ("poses.parquet", "gt.parquet", "objects.json", "frames.parquet")


def _write_csv(df: pd.DataFrame, path: Path) -> None:
    write_text_atomic(path, df.to_csv(index=False, lineterminator="\n"))


def _is_up_to_date(index: Path, run_dir: Path) -> bool:
    if not index.is_file():
        return False
    newest = max(((run_dir / n).stat().st_mtime for n in INPUTS if (run_dir / n).exists()), default=0.0)
    return index.stat().st_mtime >= newest


def main(conf: EstimatorConfig | None, poses_path: Path | None, run_dir: Path, overwrite: bool = False) -> Path:
    """Score a run and write ``run_dir/report/{summary.csv, frames.csv, index.html}``.

    Args:
        conf: unused (the run's own config is read from ``run_dir``; the stage contract passes it to every stage).
        poses_path: the estimates (None: ``run_dir/poses.parquet``, where the estimate stage writes them).
        run_dir: run directory (layout in :mod:`batchpose.report.runs`).
        overwrite: rebuild even when the report is newer than the run's tables.

    Returns:
        The report directory.

    Raises:
        DataError: ``poses.parquet`` missing or a table malformed; objects without model points.
    """
    run_dir = Path(run_dir)
    report_dir = run_dir / "report"
    index = report_dir / "index.html"
    if up_to_date("report", index, overwrite, _is_up_to_date(index, run_dir)):
        return report_dir
    run = load_run(run_dir)
    report_dir.mkdir(parents=True, exist_ok=True)
    if run.has_gt:
        per_instance, summary = scoring.score_run(run)
        frames = scoring.instance_table(run, per_instance)
    else:
        per_instance = None
        summary = scoring.detection_summary(run.poses)
        frames = scoring.detection_table(run.poses)
    pairs = scoring.pair_table(run.poses, per_instance)
    summary = scoring.with_pair_counts(summary, pairs, run.has_gt)
    verdict = scoring.verdict(pairs, run.n_frames, summary if run.has_gt else None)
    _write_csv(summary, report_dir / "summary.csv")
    _write_csv(frames, report_dir / "frames.csv")
    items, note = overlays.gallery(run, per_instance)
    write_text_atomic(index, html.report_page(run, summary, per_instance, verdict, items, note))
    log.info(
        "report: %s (%s; %d overlays%s)", index, html.verdict_text(verdict), len(items), f"; {note}" if note else ""
    )
    return report_dir


def compare(run_dirs: list[Path], out: Path) -> Path:
    """Compare runs side by side: ``out/compare.csv`` (one row per run) and ``out/index.html``.

    Args:
        run_dirs: run directories (labelled by folder name; duplicates get a suffix).
        out: output directory.

    Returns:
        The output directory.

    Raises:
        DataError: no run directories, or a run directory that cannot be loaded.
    """
    comparison = compare_runs([Path(p) for p in run_dirs])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _write_csv(comparison.table, out / "compare.csv")
    write_text_atomic(out / "index.html", html.compare_page(comparison.table, comparison.curves, comparison.notes))
    log.info("compare: %d runs -> %s", len(run_dirs), out / "index.html")
    return out

"""The job's stages, chained by :mod:`batchpose.run`: ingest -> build_templates -> estimate -> carry -> export_csv,
export_mcap -> report.

Every stage is a module with ``main(conf, inputs, run_dir, overwrite=False) -> Path``: the estimator config,
the stage's own inputs (a small frozen dataclass, or the path an earlier stage returned), the run directory;
it returns the artifact it wrote. Stages are the only code that writes a run directory.

One rule decides whether a stage has work to do (:func:`up_to_date`): its artifact exists, ``--overwrite``
was not given and the artifact is still what its inputs make. The estimate stage applies the same rule to
each (frame, object) pair as well (see :mod:`batchpose.stages.checkpoints`).
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger("batchpose")


def up_to_date(stage: str, artifact: Path, overwrite: bool, fresh: bool = True, detail: str = "") -> bool:
    """True (and says "Skipping <stage>: ...") when ``artifact`` exists, ``overwrite`` is off and ``fresh``
    (the stage's own check that the artifact still matches its inputs) holds."""
    if overwrite or not fresh or not Path(artifact).exists():
        return False
    log.info("Skipping %s: %s is up to date%s", stage, artifact, f" ({detail})" if detail else "")
    return True

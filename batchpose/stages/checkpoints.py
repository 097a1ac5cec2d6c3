"""Checkpoints of the estimate stage: what a killed run keeps, and what a rerun skips.

A worker task is a *chunk*: consecutive frames estimated in order, so that tracks run from frame to frame
within it (``track.chunk_frames``). While a worker estimates a chunk it saves, every :data:`CHECKPOINT_S`
seconds, the rows estimated since its last save (``shards/shard-<chunk>-p<part>.parquet``) and then the
sequence state the next frame starts from (``shards/chunk-<chunk>.state``: tracks, lost objects, the previous
frame). When the chunk is done the run writes all its rows as ``shards/shard-<chunk>.parquet`` and removes the
parts and the state. A killed run loses at most the work since the last save; a rerun starts each
unfinished chunk from its state, so it estimates exactly what the uninterrupted run would have, and drops
the rows of pairs already saved. Every file is written atomically: a rerun never trusts a half-written one.

The state is a pickle, like the mesh cache: a run directory is the user's own, written only by batchpose.
"""

from __future__ import annotations

import hashlib
import json
import logging
import pickle
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from batchpose.io.files import write_bytes_atomic, write_parquet_atomic
from batchpose.method.sequence import Sequence

log = logging.getLogger("batchpose")

#: A worker saves its chunk's progress at most this often (seconds): a kill loses about this much work.
CHECKPOINT_S = 1.0
#: Bumped when the state file's content changes; a state of another format is ignored (the chunk restarts).
STATE_FORMAT = 1


def chunk_key(frame_ids: Iterable[str], targets: Iterable[Iterable[str]]) -> str:
    """What a chunk is: its frames and their objects, hashed. A state saved for another chunk is not used."""
    text = json.dumps([list(frame_ids), [list(t) for t in targets]])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass
class ChunkFiles:
    """The checkpoint files of one chunk in ``shard_dir`` (chunk ids are ``c`` and its first frame's index)."""

    shard_dir: Path
    chunk_id: str

    @property
    def shard(self) -> Path:
        return self.shard_dir / f"shard-{self.chunk_id}.parquet"

    @property
    def state(self) -> Path:
        return self.shard_dir / f"chunk-{self.chunk_id}.state"

    def parts(self) -> list[Path]:
        return sorted(self.shard_dir.glob(f"shard-{self.chunk_id}-p*.parquet"))

    def load_state(self, key: str) -> tuple[int, Sequence] | None:
        """(index of the next frame to estimate, the sequence state it starts from) saved for the chunk
        ``key``; None when there is none, or it is unreadable or another chunk's (the chunk then restarts)."""
        try:
            saved = pickle.loads(self.state.read_bytes())  # our own file (see the module docstring)
            if saved["format"] == STATE_FORMAT and saved["key"] == key:
                return int(saved["next"]), saved["sequence"]
        except FileNotFoundError:
            return None
        except Exception as e:  # damaged, or pickled by another version: start the chunk again
            log.warning("%s: unreadable checkpoint (%s: %s); its chunk starts again", self.state, type(e).__name__, e)
        return None

    def save(self, rows: list[dict], next_frame: int, sequence: Sequence, key: str) -> None:
        """Save ``rows`` as the next part, then the state the frame ``next_frame`` starts from."""
        if rows:
            parts = self.parts()
            k = 1 + max((int(p.stem.rsplit("-p", 1)[1]) for p in parts), default=-1)
            write_parquet_atomic(pd.DataFrame(rows), self.shard_dir / f"shard-{self.chunk_id}-p{k:04d}.parquet")
        state = {"format": STATE_FORMAT, "key": key, "next": next_frame, "sequence": sequence}
        write_bytes_atomic(self.state, pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL))

    def finish(self, rows: list[dict]) -> None:
        """Write the chunk's shard (with the rows an earlier run saved for it) and remove its parts and state."""
        earlier = [pd.read_parquet(p) for p in [self.shard, *self.parts()] if p.is_file()]
        df = pd.concat([*earlier, pd.DataFrame(rows)], ignore_index=True) if earlier else pd.DataFrame(rows)
        if earlier:
            df = df.drop_duplicates(subset=["frame_id", "obj_name"], keep="last").reset_index(drop=True)
        write_parquet_atomic(df, self.shard)
        for p in self.parts():
            p.unlink()
        self.state.unlink(missing_ok=True)


@dataclass
class Saver:
    """When a worker saves its chunk's progress: every :data:`CHECKPOINT_S` seconds (never without files)."""

    files: ChunkFiles | None
    key: str
    since: float = field(default_factory=time.perf_counter)
    pending: list[dict] = field(default_factory=list)

    def after_frame(self, rows: list[dict], next_frame: int, sequence: Sequence) -> None:
        self.pending.extend(rows)
        if self.files is None or time.perf_counter() - self.since < CHECKPOINT_S:
            return
        self.files.save(self.pending, next_frame, sequence, self.key)
        self.pending, self.since = [], time.perf_counter()

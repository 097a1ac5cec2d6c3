"""An MCAP file opened for reading: what it holds (schemas, channels, message counts, metadata) and its
records, undecoded.

An indexed file is read through its summary and in log-time order. A file without footer/summary (a
recording cut short) is read in stream mode: the messages of all complete chunks are used, in file order,
and :meth:`McapLog.warn_if_truncated` says what was lost.
"""

from __future__ import annotations

import json
import logging
import struct
from collections import defaultdict
from collections.abc import Generator, Iterable, Iterator
from pathlib import Path
from typing import Any

from mcap.exceptions import EndOfFile, McapError
from mcap.reader import SeekingReader
from mcap.records import Attachment, Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader

from batchpose.errors import DataError
from batchpose.io.files import one_line
from batchpose.io.mcap_decode import to_ground_truth
from batchpose.io.mcap_topics import GT_TOPIC, IMAGE_SCHEMAS, MCAP_MAGIC, METADATA_NAME

try:  # zstd is how chunks are usually compressed; its errors mean a corrupt chunk
    from zstandard import ZstdError
except ImportError:  # pragma: no cover - zstandard ships with mcap's recommended extras
    ZstdError = McapError  # type: ignore[assignment,misc]

log = logging.getLogger("batchpose")

#: Errors the mcap reader raises on bad bytes (CRCValidationError is a ValueError).
_READ_ERRORS = (McapError, ValueError, struct.error, ZstdError, RuntimeError)

#: A (schema, channel, message) record, undecoded; schema None for a channel without one.
RawRecord = tuple[Schema | None, Channel, Message]


class McapLog:
    """An MCAP file's inventory, read once on opening, and its records.

    Args:
        path: the MCAP file.

    Attributes:
        schemas: schema id -> schema record.
        channels: channel id -> channel record.
        counts: channel id -> number of messages (None: the file says nothing, no statistics record).
        metadata: metadata records by name.
        profile: the header's profile ("ros1", "ros2", ...).
        library: the header's library, as a stream-mode scan read it ("" when indexed).
        gt_obj_ids: object name -> obj_id from the ground-truth messages a stream-mode scan read.
        indexed: read through its summary, in log-time order.
        truncated: no footer/summary, or it breaks off inside a record.
        lost_bytes: bytes after the last complete record of a truncated file.
        n_messages: number of messages (read or, indexed, recorded).
        start_ns: log time of its first message of any topic (where Foxglove's timeline starts); None when
            the file says nothing (no statistics record).
        end_ns: log time of its last message of any topic; None when the file says nothing.

    Raises:
        DataError: the file does not exist, is not an MCAP file (a ROS 1 bag and an SQLite database are
            named), is truncated with no complete image message, or is corrupt (CRC mismatch).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise DataError(f"{self.path}: MCAP file does not exist")
        self.size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            head = f.read(16)
            f.seek(max(0, self.size - 8))
            tail = f.read(8)
        if head.startswith(b"#ROSBAG V2.0"):
            raise DataError(f"{self.path}: a ROS 1 bag, not an MCAP file; convert it with `mcap convert BAG OUT.mcap`")
        if head.startswith(b"SQLite format 3"):
            raise DataError(
                f"{self.path}: an SQLite database (a ROS 2 .db3 bag?), not an MCAP file; convert it with "
                "`mcap convert BAG.db3 OUT.mcap` or `ros2 bag convert`"
            )
        if head[:8] != MCAP_MAGIC:
            raise DataError(
                f"{self.path}: not an MCAP file (expected magic {MCAP_MAGIC!r} at the start, got {head[:8]!r})"
            )
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.counts: dict[int, int] | None = None
        self.metadata: dict[str, dict[str, str]] = {}
        self.profile = ""
        self.library = ""
        self.gt_obj_ids: dict[str, int] = {}
        self.indexed = False
        self.truncated = False
        self.lost_bytes = 0
        self.n_messages = 0
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        if tail == MCAP_MAGIC and self.size > 16 and self._read_summary():
            self.indexed = True
        else:
            self.truncated = tail != MCAP_MAGIC
            self._scan_stream()

    # -- opening

    def _read_summary(self) -> bool:
        """Load schemas, channels and counts from the summary; False when there is no usable index."""
        try:
            with open(self.path, "rb") as f:
                reader = SeekingReader(f, validate_crcs=True)
                self.profile = reader.get_header().profile
                summary = reader.get_summary()
                if summary is None or not summary.chunk_indexes:
                    return False
                self.schemas = dict(summary.schemas)
                self.channels = dict(summary.channels)
                if summary.statistics is not None:
                    self.counts = dict(summary.statistics.channel_message_counts)
                    self.n_messages = summary.statistics.message_count
                    if self.n_messages:
                        self.start_ns = int(summary.statistics.message_start_time)
                        self.end_ns = int(summary.statistics.message_end_time)
                for m in reader.iter_metadata():
                    self.metadata[m.name] = dict(m.metadata)
        except _READ_ERRORS as e:
            log.warning("%s: cannot read the MCAP summary (%s); reading the file sequentially", self.path, one_line(e))
            return False
        return True

    def _scan_stream(self) -> None:
        """Walk the file once without an index: channels, per-channel counts and where it breaks off."""
        counts: dict[int, int] = defaultdict(int)
        data_end = False
        with open(self.path, "rb") as f:
            last_ok = 0
            try:
                for rec in StreamReader(f, validate_crcs=True).records:
                    if isinstance(rec, Message):
                        counts[rec.channel_id] += 1
                        if self.start_ns is None or rec.log_time < self.start_ns:
                            self.start_ns = int(rec.log_time)
                        if self.end_ns is None or rec.log_time > self.end_ns:
                            self.end_ns = int(rec.log_time)
                        ch = self.channels.get(rec.channel_id)
                        if ch is not None and ch.topic == GT_TOPIC:
                            self._collect_obj_ids(rec.data)
                    elif isinstance(rec, Schema):
                        self.schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        self.channels[rec.id] = rec
                    elif isinstance(rec, Metadata):
                        self.metadata[rec.name] = dict(rec.metadata)
                    elif isinstance(rec, DataEnd):
                        data_end = True
                    elif hasattr(rec, "profile"):
                        self.profile, self.library = rec.profile, str(getattr(rec, "library", ""))
                    last_ok = f.tell()
            except (EndOfFile, struct.error):
                self.truncated = True
            except CRCValidationError as e:
                raise DataError(f"{self.path}: CRC mismatch, the file is corrupt ({one_line(e)})") from None
            except _READ_ERRORS as e:
                if not self.truncated:
                    raise DataError(f"{self.path}: corrupt MCAP record ({one_line(e)})") from None
        self.counts = dict(counts)
        self.n_messages = sum(counts.values())
        self.lost_bytes = 0 if data_end else max(0, self.size - last_ok)
        if self.truncated and not any(
            self.schema_name(ch) in IMAGE_SCHEMAS and counts.get(cid) for cid, ch in self.channels.items()
        ):
            raise DataError(
                f"{self.path}: truncated MCAP (no footer/summary) and no complete chunk holds an image "
                f"message ({self.size} bytes, {self.n_messages} messages recovered)"
            )

    def _collect_obj_ids(self, data: bytes) -> None:
        """Object ids of a ground-truth message (JSON), kept in case the metadata record is lost; a message
        that does not parse is reported when the frames are read, not here."""
        try:
            self.gt_obj_ids.update(to_ground_truth(json.loads(data)).obj_ids)
        except ValueError:
            pass

    def warn_if_truncated(self, image_topic: str) -> None:
        """Warn, when the file is truncated, how many messages were read (and images on ``image_topic``),
        how many bytes were lost, and whether a batchpose log's object ids went with them."""
        if not self.truncated:
            return
        n_img = self.topic_count(image_topic)
        ids = ""
        if self.library.startswith("batchpose") and "obj_ids" not in self.metadata.get(METADATA_NAME, {}):
            ids = (
                "; the metadata record at its end (object ids) was lost too: object ids come from the "
                "ground-truth messages read"
                if self.gt_obj_ids
                else "; the metadata record at its end (object ids) was lost too: obj_id is 0 in poses.csv"
            )
        log.warning(
            "%s: truncated MCAP (no footer/summary): read %d messages (%d images on %s) from complete "
            "chunks; the last %d bytes (an incomplete record) were lost, holding an unknown number of "
            "messages%s",
            self.path,
            self.n_messages,
            n_img,
            image_topic,
            self.lost_bytes,
            ids,
        )

    # -- inventory

    def schema_name(self, ch: Channel) -> str:
        """The name of a channel's schema ("" when it has none)."""
        s = self.schemas.get(ch.schema_id)
        return s.name if s is not None else ""

    def topics(self) -> dict[str, str]:
        """topic -> schema name, in channel id order."""
        out: dict[str, str] = {}
        for cid in sorted(self.channels):
            ch = self.channels[cid]
            out.setdefault(ch.topic, self.schema_name(ch))
        return out

    def topic_count(self, topic: str) -> int | None:
        """Number of messages on ``topic`` (None: the file does not say)."""
        if self.counts is None:
            return None
        return sum(self.counts.get(cid, 0) for cid, ch in self.channels.items() if ch.topic == topic)

    def obj_id(self, name: str) -> int:
        """Object id from the ``batchpose`` metadata record; when a truncated log lost it, from the
        ground-truth messages read (0 if unknown)."""
        ids = self.metadata.get(METADATA_NAME, {}).get("obj_ids")
        if not ids:
            return int(self.gt_obj_ids.get(name, 0))
        try:
            return int(json.loads(ids).get(name, 0))
        except (ValueError, AttributeError):
            return 0

    # -- records

    def iter_raw(self, topics: Iterable[str] | None = None) -> Generator[RawRecord, None, None]:
        """Yield (schema, channel, message) records, undecoded: log-time order when the file is indexed,
        file order otherwise (stopping silently where a truncated file breaks off).

        Raises:
            DataError: a chunk fails its CRC or cannot be decompressed.
        """
        wanted = set(topics) if topics is not None else None
        with open(self.path, "rb") as f:
            if self.indexed:
                it = SeekingReader(f, validate_crcs=True).iter_messages(
                    topics=sorted(wanted) if wanted is not None else None, log_time_order=True
                )
            else:
                it = self._iter_stream(f, wanted)
            while True:
                try:
                    item = next(it)
                except StopIteration:
                    return
                except CRCValidationError as e:
                    raise DataError(f"{self.path}: CRC mismatch, the file is corrupt ({one_line(e)})") from None
                except _READ_ERRORS as e:
                    raise DataError(f"{self.path}: corrupt MCAP data ({type(e).__name__}: {one_line(e)})") from None
                yield item

    def _iter_stream(self, f: Any, wanted: set[str] | None) -> Iterator[RawRecord]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        try:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id) or self.channels.get(rec.channel_id)
                    if ch is None:
                        raise DataError(f"{self.path}: message on unknown channel id {rec.channel_id}")
                    if wanted is None or ch.topic in wanted:
                        yield schemas.get(ch.schema_id) or self.schemas.get(ch.schema_id), ch, rec
                elif isinstance(rec, Footer):
                    return
        except (EndOfFile, struct.error):
            if not self.truncated:
                raise DataError(f"{self.path}: unexpected end of file") from None

    def iter_attachments(self) -> Iterator[Attachment]:
        """Yield the file's attachment records.

        Raises:
            DataError: the file ends early (not truncated when opened) or a record is corrupt.
        """
        with open(self.path, "rb") as f:
            try:
                if self.indexed:
                    yield from SeekingReader(f, validate_crcs=True).iter_attachments()
                    return
                for rec in StreamReader(f, validate_crcs=True).records:
                    if isinstance(rec, Attachment):
                        yield rec
            except (EndOfFile, struct.error):
                if not self.truncated:
                    raise DataError(f"{self.path}: unexpected end of file") from None
            except _READ_ERRORS as e:
                raise DataError(f"{self.path}: corrupt MCAP data ({type(e).__name__}: {one_line(e)})") from None

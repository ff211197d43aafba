"""A rosbag2 writer that a crash cannot leave unreadable: rosbags' ``Writer``, flushed as it goes.

rosbags' :class:`~rosbags.rosbag2.Writer` writes the bag (MCAP or sqlite3, every topic with its
full message definition and type hash) but only makes it readable at ``close()``: MCAP's
summary and footer, sqlite3's commit and ``metadata.yaml`` are written there. A recorder can be
killed (``kill -9``, power) or run out of disk, so :class:`CrashSafeWriter` keeps the folder a
readable bag between flushes (every ``flush_s``):

- MCAP: every closed chunk is followed at once by a provisional end — a DataEnd record and a
  Footer without summary (``summary_start = 0``; the summary section is optional in the MCAP
  spec, readers then scan the chunks) — which the next chunk overwrites. So the file on disk
  always ends in a complete chunk and a valid footer, except while a chunk is being written.
- sqlite3: the open transaction is committed.
- then ``metadata.yaml`` is rewritten (atomically) with the counts so far.

The bag is readable from the start: :meth:`CrashSafeWriter.open` ends the new MCAP at once and
writes ``metadata.yaml`` (no messages) before any message arrives. A full disk keeps the bag as
of its last flush, the MCAP cut where that flush's ``metadata.yaml`` counted it; a small reserve
file written at open (:data:`RESERVE`) is given back first, so that the rollback and the last
``metadata.yaml`` fit. :attr:`CrashSafeWriter.kept` then holds what a reader will find.

:func:`recover` finishes a bag left mid-write (the MCAP cut after its last complete record,
``metadata.yaml`` recounted from the file): what ``--recover`` runs. The writer relies on
rosbags' MCAP storage writing each closed chunk straight to its file (``bio``, ``chunks``,
``chunk``); :func:`_check_storage` refuses a rosbags version where that is not so.
"""

from __future__ import annotations

import errno
import os
import sqlite3
import struct
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from rosbags.rosbag2 import StoragePlugin, Writer

from tagtrail.errors import SourceError, StorageError, storage_error
from tagtrail.io import msgs
from tagtrail.io.layouts import atomic_write_text

MAGIC = b"\x89MCAP0\r\n"
# DataEnd (op 0x0F, crc 0 = not computed) + Footer (op 0x02: summary_start 0, summary offset 0,
# crc 0) + magic: the end of an MCAP with no summary section.
TAIL = b"\x0f" + struct.pack("<QI", 4, 0) + b"\x02" + struct.pack("<QQQI", 20, 0, 0, 0) + MAGIC
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
RESERVE = ".tagtrail-reserve"  # space held back for a full disk's clean-up (module docstring)
RESERVE_BYTES = 16 * 1024


@dataclass(frozen=True)
class TopicCount:
    """One topic of ``metadata.yaml``."""

    topic: str
    msgtype: str
    digest: str
    count: int


def metadata_text(
    storage: str, file_name: str, topics: Sequence[TopicCount], t_min: int, t_max: int
) -> str:
    """``metadata.yaml`` as rosbags' ``Writer.close()`` writes it (rosbag2 version 9)."""
    n = sum(t.count for t in topics)
    start = t_min if n else 0
    duration = max(0, t_max - t_min) if n else 0
    info = {
        "version": 9,
        "storage_identifier": storage,
        "relative_file_paths": [file_name],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": n,
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": t.topic,
                    "type": t.msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": [],
                    "type_description_hash": t.digest,
                },
                "message_count": t.count,
            }
            for t in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": [
            {
                "path": file_name,
                "starting_time": {"nanoseconds_since_epoch": start},
                "duration": {"nanoseconds": duration},
                "message_count": n,
            }
        ],
        "custom_data": None,
        "ros_distro": "rosbags",
    }
    return yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)


def _check_storage(storage: Any, kind: str) -> None:
    need = ("bio", "chunks", "chunk", "close_chunk") if kind == "mcap" else ("conn",)
    missing = [a for a in need if not hasattr(storage, a)]
    if missing:
        raise StorageError(
            f"this rosbags version's {kind} writer has no {', '.join(missing)}; "
            "tagtrail stream record needs rosbags >= 0.10.4 as pinned"
        )


class CrashSafeWriter:
    """Write a rosbag2 folder ``out`` (``storage`` mcap | sqlite3), flushed every ``flush_s``.

    ``write(topic, msgtype, t_ns, cdr)`` takes the CDR bytes as received (written unchanged)
    and ``t_ns`` as the log time. Not thread-safe: one thread opens, writes, flushes and closes.
    """

    def __init__(self, out: Path, storage: str = "mcap", flush_s: float = 1.0) -> None:
        self.out = Path(out)
        self.kind = storage
        self.flush_s = flush_s
        if self.out.exists():
            raise SourceError(
                f"{self.out} exists already; record into a new folder (or "
                f"`tagtrail stream record --recover {self.out}` to finish a "
                "recording that was killed)"
            )
        self.writer = Writer(self.out, version=9, storage_plugin=STORAGES[storage])
        self.file = self.out / f"{self.out.name}.{'mcap' if storage == 'mcap' else 'db3'}"
        self.conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}
        self.t_min, self.t_max = 2**63 - 1, 0
        self.size = 0  # bytes of message data written
        self._tail_at: int | None = None  # MCAP: offset of the provisional end
        self._good_at: int | None = None  # MCAP: offset of the last end written out in full
        self._chunks = 0
        self._next_flush = time.monotonic() + flush_s
        self._dirty = False
        self._meta_at: int | None = None  # MCAP: where the file ends as metadata.yaml counts it
        self._meta_counts: dict[str, int] = {}
        self.kept: dict[str, int] | None = None  # after abort(): the messages the bag holds
        self.opened = False  # False: no bag folder (never opened, or removed by open's failure)

    def open(self) -> None:
        """Create the folder, the storage file, the reserve and a first ``metadata.yaml`` (in
        the thread that writes: sqlite3 connections belong to their thread). The bag is
        readable from here on; if the disk cannot hold even that, nothing is left behind."""
        try:
            self.writer.open()
            _check_storage(self.writer.storage, self.kind)
            (self.out / RESERVE).write_bytes(b"\0" * RESERVE_BYTES)
            if self.kind == "mcap":
                self._end_mcap(sync=True)
            else:
                self.writer.storage.conn.commit()  # type: ignore[union-attr]
            self._write_metadata()
        except OSError as err:
            self._discard()
            if err.filename is None:  # a failed write names no file
                err.filename = str(self.out)
            raise (storage_error(err, "record") or err) from err
        except BaseException:
            self._discard()
            raise
        self.opened = True

    def _discard(self) -> None:
        """Remove the bag folder this writer has just created (nothing was recorded in it)."""
        st: Any = self.writer.storage
        self.writer.storage = None
        if st is not None:
            try:
                st.abort()
            except Exception:  # noqa: BLE001 - a full disk: the folder goes anyway
                pass
        for name in (self.file.name, RESERVE, "metadata.yaml"):
            (self.out / name).unlink(missing_ok=True)
        for p in self.out.glob(".metadata.yaml.*"):  # atomic_write_text's temporary file
            p.unlink(missing_ok=True)
        try:
            self.out.rmdir()
        except OSError:
            pass  # not empty: something else wrote there; leave it

    def write(self, topic: str, msgtype: str, t_ns: int, cdr: bytes) -> None:
        conn = self.conns.get(topic)
        if conn is None:
            conn = self.conns[topic] = self.writer.add_connection(
                topic, msgtype, typestore=msgs.typestore()
            )
            self.counts[topic] = 0
        st: Any = self.writer.storage
        self.writer.write(conn, t_ns, cdr)  # MCAP: the file sits at the provisional end
        self.counts[topic] += 1
        self.t_min, self.t_max = min(self.t_min, t_ns), max(self.t_max, t_ns)
        self.size += len(cdr)
        self._dirty = True
        if self.kind == "mcap" and len(st.chunks) != self._chunks:
            self._end_mcap(sync=False)  # rosbags closed a full chunk: end the file after it
        self.maybe_flush()

    def maybe_flush(self) -> None:
        """:meth:`flush` if ``flush_s`` has passed since the last one."""
        if time.monotonic() >= self._next_flush:
            self.flush()

    def _end_mcap(self, sync: bool) -> None:
        st: Any = self.writer.storage
        if st.chunk.msgs:
            if self._tail_at is not None:
                st.bio.seek(self._tail_at)
            st.close_chunk()
        self._chunks = len(st.chunks)
        self._tail_at = st.bio.tell()
        st.bio.write(TAIL)
        st.bio.flush()
        if sync:
            os.fsync(st.bio.fileno())
        self._good_at = self._tail_at  # everything before it is on disk, not just buffered
        st.bio.seek(self._tail_at)  # the next chunk overwrites this end

    def flush(self) -> None:
        """Make everything written so far readable on disk (module docstring)."""
        self._next_flush = time.monotonic() + self.flush_s
        if not self._dirty:
            return
        if self.kind == "mcap":
            self._end_mcap(sync=True)
        else:
            self.writer.storage.conn.commit()  # type: ignore[union-attr]
        self._write_metadata()
        self._dirty = False

    def topic_counts(self) -> list[TopicCount]:
        return [
            TopicCount(c.topic, c.msgtype, c.digest, self.counts[t]) for t, c in self.conns.items()
        ]

    def _write_metadata(self) -> None:
        atomic_write_text(
            self.out / "metadata.yaml",
            metadata_text(self.kind, self.file.name, self.topic_counts(), self.t_min, self.t_max),
        )
        self._meta_at = self._good_at
        self._meta_counts = dict(self.counts)

    def close(self) -> None:
        """Close the bag as rosbags does (MCAP summary, sqlite3 metadata, ``metadata.yaml``)."""
        st: Any = self.writer.storage
        if st is None:
            return
        if self.kind == "mcap" and self._tail_at is not None:
            st.bio.seek(self._tail_at)
        (self.out / RESERVE).unlink(missing_ok=True)  # rosbags' summary and metadata fit
        self.writer.close()

    def abort(self) -> None:
        """After a failed write (a full disk): keep the bag as of the last flush.

        The reserve is given back first. MCAP: the file is cut where the last ``metadata.yaml``
        counted it and the end written again (the same bytes: no new space needed); sqlite3: the
        open transaction is rolled back and ``metadata.yaml`` rewritten from the file if the
        last flush committed more than it counted. :attr:`kept` = the messages a reader finds.
        """
        st: Any = self.writer.storage
        self.writer.storage = None
        (self.out / RESERVE).unlink(missing_ok=True)
        for p in self.out.glob("metadata.yaml.tmp"):  # rosbags' close() stopped half-way
            p.unlink(missing_ok=True)
        if st is None:
            return
        if self.kind == "mcap":
            try:
                st.bio.close()
            except OSError:
                pass  # the buffered bytes that did not fit are dropped below
            with open(self.file, "r+b") as f:  # what no metadata.yaml counted is not kept
                f.truncate(self._meta_at if self._meta_at is not None else 0)
                if self._meta_at is not None:
                    f.seek(self._meta_at)
                    f.write(TAIL)
            self.kept = dict(self._meta_counts)
            return
        try:
            st.conn.rollback()
        finally:
            st.conn.close()
        topics, t_min, t_max = _count_sqlite(self.file)
        self.kept = {t.topic: t.count for t in topics if t.count}
        if self.kept != {t: n for t, n in self._meta_counts.items() if n}:
            atomic_write_text(
                self.out / "metadata.yaml",
                metadata_text(self.kind, self.file.name, topics, t_min, t_max),
            )


def _records(f: Any, size: int) -> Iterator[tuple[int, int, int]]:
    """``(opcode, start, end)`` of each complete MCAP record after the magic."""
    pos = len(MAGIC)
    while pos + 9 <= size:
        f.seek(pos)
        op, length = struct.unpack("<BQ", f.read(9))
        end = pos + 9 + length
        if end > size:
            return
        yield op, pos, end
        pos = end


def recover(out: Path) -> str:
    """Finish a bag whose recorder was killed: returns what was done (one line).

    MCAP: cut after the last complete record before any end, end it without summary (module
    docstring); both storages: ``metadata.yaml`` recounted from the file.
    """
    out = Path(out)
    files = sorted(out.glob("*.mcap")) + sorted(out.glob("*.db3"))
    if len(files) != 1:
        raise SourceError(
            f"{out}: not a recording of tagtrail stream record (no single .mcap or .db3 file in it)"
        )
    path = files[0]
    (out / RESERVE).unlink(missing_ok=True)
    try:
        if path.suffix == ".mcap":
            topics, t_min, t_max, cut = _recover_mcap(path)
            kind = "mcap"
        else:
            topics, t_min, t_max = _count_sqlite(path)
            kind, cut = "sqlite3", ""
        atomic_write_text(
            out / "metadata.yaml", metadata_text(kind, path.name, topics, t_min, t_max)
        )
    except OSError as err:
        raise storage_error(err, "recover") or SourceError(f"{path}: {err}") from err
    n = sum(t.count for t in topics)
    listing = ", ".join(f"{t.topic} {t.count}" for t in topics) or "no messages"
    return f"recovered {out}: {n} messages ({listing}){cut}"


def _recover_mcap(path: Path) -> tuple[list[TopicCount], int, int, str]:
    from mcap.reader import make_reader

    size = path.stat().st_size
    cut = ""
    with open(path, "r+b") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise SourceError(f"{path}: not an MCAP file")
        f.seek(max(size - 29 - len(MAGIC), 0))
        ending = f.read()
        if not (ending.endswith(MAGIC) and ending[:9] == b"\x02" + struct.pack("<Q", 20)):
            end = len(MAGIC)  # no valid footer: keep every complete record, end the file there
            for op, _start, stop in _records(f, size):
                if op == 0x0F:
                    break
                end = stop
            f.truncate(end)
            f.seek(end)
            f.write(TAIL)
            f.flush()
            os.fsync(f.fileno())
            cut = f"; cut after its last complete record (byte {end} of {size})"
    store = msgs.typestore()
    counts: dict[int, int] = {}
    chans: dict[int, tuple[str, str]] = {}
    t_min, t_max = 2**63 - 1, 0
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            chans[channel.id] = (channel.topic, schema.name if schema else "")
            counts[channel.id] = counts.get(channel.id, 0) + 1
            t_min, t_max = min(t_min, message.log_time), max(t_max, message.log_time)
    topics = [TopicCount(t, m, _digest(store, m), counts[c]) for c, (t, m) in chans.items()]
    return topics, t_min, t_max, cut


def _digest(store: Any, msgtype: str) -> str:
    """The type hash rosbag2 records; empty for a type this typestore does not know (a bag
    of another tool: its messages are read all the same)."""
    try:
        return str(store.hash_rihs01(msgtype))
    except Exception:  # noqa: BLE001 - rosbags raises its own errors for unknown types
        return ""


def _count_sqlite(path: Path) -> tuple[list[TopicCount], int, int]:
    try:
        con = sqlite3.connect(f"file:{path}?mode=rw", uri=True)
        try:
            rows = con.execute(
                "SELECT t.name, t.type, t.type_description_hash, COUNT(m.id), MIN(m.timestamp), "
                "MAX(m.timestamp) FROM topics t LEFT JOIN messages m ON m.topic_id = t.id "
                "GROUP BY t.id ORDER BY t.id"
            ).fetchall()
        finally:
            con.close()
    except sqlite3.DatabaseError as err:
        raise SourceError(f"{path}: not a readable rosbag2 sqlite3 file: {err}") from err
    topics = [TopicCount(r[0], r[1], r[2], int(r[3])) for r in rows]
    lows = [r[4] for r in rows if r[4] is not None]
    highs = [r[5] for r in rows if r[5] is not None]
    return topics, min(lows, default=0), max(highs, default=0)


def is_full_disk(err: BaseException) -> bool:
    """A write refused for lack of space (OSError, or sqlite3's own "disk is full")."""
    if isinstance(err, OSError):
        return err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
    return isinstance(err, sqlite3.OperationalError) and "full" in str(err)

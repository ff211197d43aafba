"""The exception tree. User mistakes exit 2 with one line; failures inside a stage exit 1."""

from __future__ import annotations

import errno
import os
import sys
from typing import TextIO


class TagtrailError(Exception):
    """Base of every error tagtrail raises on purpose."""

    exit_code = 2


class SpecError(TagtrailError):
    """pipeline.yaml or a command line is invalid (bad YAML, unknown stage/parameter, bad value)."""


class SourceError(TagtrailError):
    """An input file, folder, bag or topic is missing or unreadable."""


class DataError(TagtrailError):
    """The data cannot give a result (no tags, a disconnected tag graph, too few common tags)."""


class DisconnectedTagGraph(DataError):
    """Some tags are not connected to the anchor and the pipeline was told to fail on it."""


class CameraModelError(SourceError):
    """A camera model that cannot be used (e.g. a lens distortion not invertible over the image)."""


class SessionError(TagtrailError):
    """A zenoh session cannot be opened (a port in use, a bad locator, no router)."""


class ArtifactError(TagtrailError):
    """An artifact the store had verified is gone or damaged while in use (another process
    removed it, the disk failed): rerun, and the store recomputes it."""

    exit_code = 1


class StorageError(TagtrailError):
    """The file system refused a write (full disk, read-only project, no permission)."""


class StageError(TagtrailError):
    """An unexpected failure inside a stage; names the stage and dataset."""

    exit_code = 1

    def __init__(self, stage: str, dataset: str, cause: BaseException) -> None:
        super().__init__(f"stage {stage} [{dataset}] failed: {type(cause).__name__}: {cause}")
        self.stage = stage
        self.dataset = dataset
        self.cause = cause


STORAGE_ERRNOS = frozenset(
    {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG}
)


def storage_error(err: OSError, what: str = "") -> StorageError | None:
    """The one-line :class:`StorageError` for a refused write, or None for other OS errors."""
    if err.errno not in STORAGE_ERRNOS:
        return None
    where = f"{what}: " if what else ""
    # the system's words for the errno: pyarrow's OSError says "[errno 28] No space left on
    # device", Python's "No space left on device"
    return StorageError(
        f"{where}cannot write {err.filename or 'a file'}: {os.strerror(err.errno)} "
        "(free space or make the folder writable, then rerun; nothing partial "
        "was kept)"
    )


MAX_LINE = 1000  # characters of an error line: a message quoting a value never runs on


def abbreviate(text: str, limit: int = 300) -> str:
    """``text`` cut to ``limit`` characters, an ellipsis marking the cut."""
    return text if len(text) <= limit else text[: limit - 1] + "…"


def short_repr(value: object, limit: int = 80) -> str:
    """A bounded ``repr`` for messages: nested containers shown a few levels and items deep
    (cheap even for a value of 10^9 shared items), cut to ``limit`` characters."""
    import reprlib

    r = reprlib.Repr()  # (keyword arguments from Python 3.12)
    r.maxlevel, r.maxstring, r.maxother = 3, limit, limit
    r.maxtuple = r.maxlist = r.maxdict = r.maxset = r.maxfrozenset = 6
    return abbreviate(r.repr(value), limit)


def one_line(text: object) -> str:
    """A message folded onto one line: users and scripts read exactly one ``error:`` line."""
    return " ".join(str(text).split())


def report(err: TagtrailError, file: TextIO | None = None) -> int:
    """Print ``error: <one line>`` on stderr and return the error's exit code."""
    where = getattr(err, "log_path", None)
    tail = f" (traceback in {where})" if where else ""
    print(f"error: {abbreviate(one_line(err), MAX_LINE)}{tail}", file=file or sys.stderr)
    return err.exit_code

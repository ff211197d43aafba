"""Content-addressed artifact store under ``artifacts/``.

An entry is ``objects/<stage>/<key>/``: one file per output (``<name>.parquet`` or
``<name>.json``) and ``manifest.json`` listing each file's sha256. Entries are written in a
temporary folder and renamed into place, so a reader sees a whole entry or none; an entry whose
manifest is missing or whose files do not match it (a crash, a manual edit, a bit flip) is a
cache miss and is replaced. Source files are hashed by content once and remembered by
(path, size, mtime) in ``sources.json``.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from tagtrail import faults
from tagtrail.errors import ArtifactError, SourceError
from tagtrail.io.camera_files import split_camera_path
from tagtrail.io.layouts import TEMP_PREFIX, atomic_write_text
from tagtrail.runner.paths import clean_temp_files, clear_empty_obstacle, inside, is_temp_dir
from tagtrail.schemas import documents
from tagtrail.schemas.artifacts import conform


def canonical_json(obj: Any) -> str:
    """Deterministic JSON (sorted keys, numpy scalars/arrays and paths converted)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_default)


def pretty_json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, indent=2, default=_default) + "\n"


def _default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def file_sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


class SourceHasher:
    """Content hashes of source files and folders, remembered by (path, size, mtime_ns)."""

    def __init__(self, cache_file: Path) -> None:
        self.cache_file = cache_file
        self._cache: dict[str, list[Any]] = {}
        self._dirty = False
        if cache_file.is_file():
            try:
                self._cache = json.loads(cache_file.read_text())
            except (OSError, ValueError):
                self._cache = {}

    def _file(self, path: Path) -> str:
        st = path.stat()
        key = str(path.resolve())
        hit = self._cache.get(key)
        if hit and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
            return str(hit[2])
        digest = file_sha256(path)
        self._cache[key] = [st.st_size, st.st_mtime_ns, digest]
        self._dirty = True
        return digest

    def hash_camera(self, path: Path) -> str:
        """The hash of a camera file, ``FILE#NAME`` (a camchain's camera) with the name."""
        file, name = split_camera_path(path)
        return self.hash(file) if name is None else f"{self.hash(file)}#{name}"

    def hash(self, path: Path) -> str:
        """sha256 over a file, or over a folder's files (relative names + content hashes)."""
        if path.is_file():
            return self._file(path)
        if not path.is_dir():
            raise SourceError(f"{path}: no such file or folder")
        h = hashlib.sha256()
        for f in sorted(p for p in path.rglob("*") if p.is_file()):
            h.update(f"{f.relative_to(path).as_posix()}\0{self._file(f)}\n".encode())
        return h.hexdigest()

    def save(self) -> None:
        """Write the remembered hashes (``run`` only, under the store's lock)."""
        if not self._dirty:
            return
        atomic_write_text(self.cache_file, json.dumps(self._cache))
        self._dirty = False


def _rows(value: Any) -> int | None:
    return len(value) if isinstance(value, pd.DataFrame) else None


class Store:
    """The artifact store rooted at ``artifacts/``."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.objects = self.root / "objects"
        self.tmp = self.root / "tmp"
        self._verified: dict[Path, dict[str, Any]] = {}
        self._held = 0  # depth of lock() in this process

    def entry(self, stage: str, key: str) -> Path:
        return self.objects / stage / key

    def lookup(self, stage: str, key: str) -> dict[str, Any] | None:
        """The manifest of a complete, intact entry, else None (a miss, never an error)."""
        d = self.entry(stage, key)
        if d in self._verified:
            return self._verified[d]
        try:
            manifest = json.loads((d / "manifest.json").read_text())
            for out in manifest["outputs"].values():
                f = d / out["file"]
                if f.stat().st_size != out["size"] or file_sha256(f) != out["sha256"]:
                    return None
        except (OSError, ValueError, KeyError, TypeError):
            return None
        self._verified[d] = manifest
        return manifest  # type: ignore[no-any-return]

    def write(
        self, stage: str, key: str, outputs: dict[str, Any], record: dict[str, Any]
    ) -> dict[str, Any]:
        """Write all outputs of one stage run as a new entry, atomically."""
        self.tmp.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=self.tmp, prefix=f"{TEMP_PREFIX}{stage}-{key[:12]}-"))
        try:
            files: dict[str, Any] = {}
            for name, value in outputs.items():
                if isinstance(value, pd.DataFrame):
                    fname = f"{name}.parquet"
                    pq.write_table(conform(f"{stage}.{name}", value), tmp / fname)
                else:  # a JSON document (schemas.documents validates the declared ones)
                    fname = f"{name}.json"
                    (tmp / fname).write_text(pretty_json(documents.dump(f"{stage}.{name}", value)))
                f = tmp / fname
                faults.point(f"store:{stage}")
                files[name] = {
                    "file": fname,
                    "sha256": file_sha256(f),
                    "size": f.stat().st_size,
                    "rows": _rows(value),
                }
            manifest = {"stage": stage, "key": key, "outputs": files, "record": record}
            (tmp / "manifest.json").write_text(pretty_json(manifest))
            final = self.entry(stage, key)
            inside(self.objects, stage, key)  # no symlink leads the entry out of the store
            final.parent.mkdir(parents=True, exist_ok=True)
            if final.is_symlink() or final.is_file():  # never deletes through a link
                final.unlink()
            elif final.exists():  # a corrupt entry under the same key: move it aside first
                shutil.rmtree(final)
            os.replace(tmp, final)
        except BaseException as err:
            shutil.rmtree(tmp, ignore_errors=True)
            if isinstance(err, OSError) and err.filename is None:
                err.filename = str(self.entry(stage, key))
            raise
        self._verified[final] = manifest
        return manifest

    def load(self, stage: str, key: str, output: str) -> Any:
        manifest = self.lookup(stage, key)
        if manifest is None or output not in manifest["outputs"]:
            raise ArtifactError(
                f"artifact {stage}.{output} ({key[:12]}) is missing or corrupt; "
                "rerun to recompute it"
            )
        f = self.entry(stage, key) / manifest["outputs"][output]["file"]
        if f.suffix == ".json":
            return documents.load(f"{stage}.{output}", json.loads(f.read_text()))
        return pd.read_parquet(f)

    @contextmanager
    def lock(self) -> Iterator[None]:
        """Exclusive lock on the store for the duration of a run (waits for another run).
        Re-entrant within one Store, so a run and its export can share one holding."""
        if self._held:
            self._held += 1
            try:
                yield
            finally:
                self._held -= 1
            return
        self.root.mkdir(parents=True, exist_ok=True)
        clear_empty_obstacle(self.root / ".lock", folder=False)
        with open(self.root / ".lock", "w") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                print("waiting for another tagtrail run to finish…", file=sys.stderr)
                fcntl.flock(fh, fcntl.LOCK_EX)
            self._held = 1
            try:
                self._clean_tmp()
                yield
            finally:
                self._held = 0
                fcntl.flock(fh, fcntl.LOCK_UN)

    def _clean_tmp(self) -> None:
        """Remove leftovers of killed runs (only called while holding the lock): tagtrail's own
        temporary names only (``.tagtrail-tmp-…``), never through a symlink."""
        if self.tmp.is_dir() and not self.tmp.is_symlink():
            for e in os.scandir(self.tmp):
                if is_temp_dir(e.name) and e.is_dir(follow_symlinks=False):
                    shutil.rmtree(e.path, ignore_errors=True)
        clean_temp_files(self.root)
        runs = self.root / "runs"
        if runs.is_dir() and not runs.is_symlink():
            for folder in (runs, *(p for p in runs.iterdir() if p.is_dir() and not p.is_symlink())):
                clean_temp_files(folder)

    def record_path(self, dataset: str, stage: str) -> Path:
        return inside(self.root / "runs", dataset, f"{stage}.json")

    def save_record(self, dataset: str, stage: str, record: dict[str, Any]) -> None:
        atomic_write_text(self.record_path(dataset, stage), pretty_json(record))

    def last_record(self, dataset: str, stage: str) -> dict[str, Any] | None:
        try:
            rec: dict[str, Any] = json.loads(self.record_path(dataset, stage).read_text())
            return rec
        except (OSError, ValueError):
            return None

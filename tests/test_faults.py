"""Fault injection on the real pipeline (issue 10): kill -9 inside every stage, inside the store's
write and inside every exporter; a full disk; a damaged output; a damaged cache entry. After each,
a plain ``tagtrail run`` gives outputs byte-identical to an undisturbed run, with no stray files.

Kills use ``TAGTRAIL_FAULT=kill@<point>`` (``tagtrail/faults.py``): SIGKILL at a named point.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
from pathlib import Path

import pytest

from tagtrail.stages import REGISTRY
from tests.cli_helpers import TEMP, demo_project, files, stray, tagtrail

pytestmark = pytest.mark.slow  # the crash suite: kill -9 everywhere, a full disk (make test-all)

EXPORTS = [e.name for m in REGISTRY.values() for e in getattr(m, "EXPORTS", ())]


@pytest.fixture(scope="module")
def data(room_images: Path) -> Path:
    return room_images


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory, data: Path) -> dict[str, bytes]:
    """The outputs of an undisturbed run."""
    project = demo_project(tmp_path_factory.mktemp("good"), data)
    done = tagtrail(project, "run")
    assert done.returncode == 0, done.stderr
    return files(project / "outputs")


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory, data: Path) -> Path:
    """A project whose first run was killed while the store wrote extract's entry."""
    project = demo_project(tmp_path_factory.mktemp("faults"), data)
    killed = tagtrail(project, "run", fault="kill@store:extract")
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert not (project / "outputs").exists()
    return project


def recover_and_compare(project: Path, good: dict[str, bytes]) -> str:
    done = tagtrail(project, "run")
    assert done.returncode == 0, done.stderr
    assert files(project / "outputs") == good
    assert stray(project) == []
    return done.stdout


def test_killed_first_run_recovers(project: Path, good: dict[str, bytes]) -> None:
    out = recover_and_compare(project, good)
    assert "extract [reference]" in out and "never run" in out


@pytest.mark.parametrize("stage", list(REGISTRY))
@pytest.mark.parametrize("where", ["stage", "store"])
def test_kill_9_inside_every_stage(
    project: Path, good: dict[str, bytes], stage: str, where: str
) -> None:
    recover_and_compare(project, good)
    shutil.rmtree(project / "artifacts" / "objects" / stage)  # so the stage runs again
    killed = tagtrail(project, "run", fault=f"kill@{where}:{stage}")
    assert killed.returncode == -signal.SIGKILL, (killed.stdout, killed.stderr)
    out = recover_and_compare(project, good)
    assert re.search(rf"^{stage} \[\S+\] +ran ", out, re.M), out


@pytest.mark.parametrize("exporter", EXPORTS)
def test_kill_9_inside_every_exporter(project: Path, good: dict[str, bytes], exporter: str):
    recover_and_compare(project, good)
    shutil.rmtree(project / "outputs")
    killed = tagtrail(project, "run", fault=f"kill@export:{exporter}")
    assert killed.returncode == -signal.SIGKILL, (killed.stdout, killed.stderr)
    recover_and_compare(project, good)


def test_kill_9_while_an_output_file_is_half_written(project, good) -> None:
    recover_and_compare(project, good)
    (project / "outputs" / "reference" / "map.png").unlink()
    killed = tagtrail(project, "run", fault="kill@write:map.png")
    assert killed.returncode == -signal.SIGKILL
    assert any(TEMP.match(p.name) for p in (project / "outputs" / "reference").iterdir())
    recover_and_compare(project, good)


def test_damaged_cache_entry_is_recomputed(project: Path, good: dict[str, bytes]) -> None:
    recover_and_compare(project, good)
    entry = next((project / "artifacts" / "objects" / "pnp").iterdir())
    parquet = entry / "observations.parquet"
    raw = bytearray(parquet.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    parquet.write_bytes(bytes(raw))
    out = recover_and_compare(project, good)
    assert re.search(r"^pnp \[\S+\] +ran .*artifact missing or corrupt", out, re.M), out


def test_damaged_output_files_are_restored(project: Path, good: dict[str, bytes]) -> None:
    recover_and_compare(project, good)
    out = project / "outputs"
    (out / "reference" / "trajectory.csv").write_bytes(b"stamp_sec,stamp")
    (out / "query_1" / "summary.json").write_text("{garbage")
    (out / "query_2" / "relocalization.png").unlink()
    (out / "reference" / ".tagtrail-export.json").unlink()
    recover_and_compare(project, good)


def _mount(*args: str) -> bool:
    return subprocess.run(["mount", *args], capture_output=True).returncode == 0


@pytest.mark.parametrize("size_kb", [48, 250, 600, 1000])
def test_full_disk_fails_in_one_line_and_keeps_nothing_partial(tmp_path, data, good, size_kb):
    """The project lives on a tmpfs of ``size_kb``: the run stops with one line wherever the disk
    fills (a stage's entry, the run log, an export), then, with room again, completes."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if not _mount("-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(mnt)):
        if os.environ.get("CI") == "true":
            pytest.fail("CI runs as root and must be able to mount a tmpfs")
        pytest.skip("cannot mount a tmpfs here (not root)")
    try:
        project = demo_project(mnt / "p", data)
        full = tagtrail(project, "run")
        if full.returncode == 0:
            pytest.fail(f"{size_kb} kB was enough; the test wants a disk that fills")
        errors = [ln for ln in full.stderr.splitlines() if ln.startswith("error")]
        assert full.returncode == 2 and len(errors) == 1, full.stderr
        assert full.stderr.strip().splitlines()[-1] == errors[0]
        assert re.match(rf"error: .*cannot write {mnt}/p/\S+: No space left on device", errors[0])
        assert _mount("-o", "remount,size=64m", str(mnt))
        recover_and_compare(project, good)
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_a_refused_write_says_it_in_the_systems_words() -> None:
    """pyarrow's OSError on a full disk reads "[errno 28] No space left on device": the one
    line says what Python's own does, whichever library hit the full disk (the full-disk test
    above matches it, wherever the disk fills)."""
    import errno

    from tagtrail.errors import storage_error

    for strerror in ("[errno 28] No space left on device", "No space left on device"):
        err = storage_error(OSError(errno.ENOSPC, strerror, "/data/p/a.parquet"), "pnp [ref]")
        assert err is not None
        assert str(err).startswith("pnp [ref]: cannot write /data/p/a.parquet: No space left")

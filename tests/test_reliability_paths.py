"""Where tagtrail writes and deletes (issue 26, items 1, 2, 3, 6, 8, 12, 13, 15): no symlink leads
a write or a delete out of the project, only tagtrail's own temporary files are removed,
read-only commands write nothing, state is written under the store's lock, and a path in the way
of an output is replaced only when empty. Real CLI calls on real detection bags."""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tagtrail.cli import main
from tagtrail.io.layouts import atomic_write_text, remove_stale_temps
from tagtrail.runner.paths import OUTPUT_FILES
from tests.cli_helpers import one_error_line, tagtrail

QUERY_INPUTS = {
    "trajectory.tag_map": "reference:optimize.tag_map",
    "align.tag_map": "reference:optimize.tag_map",
}


def tree(root: Path) -> dict[str, bytes]:
    """Every file below ``root`` (not following symlinks) with its bytes; links as their target."""
    out: dict[str, bytes] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath, name)
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = f"-> {os.readlink(p)}".encode()
            elif p.is_file():
                out[rel] = p.read_bytes()
    return out


def stamps(root: Path) -> dict[str, int]:
    """Every path below ``root`` with its mtime (a rewrite with equal bytes still shows)."""
    return {str(p.relative_to(root)): p.lstat().st_mtime_ns for p in root.rglob("*")}


def write_pipeline(folder: Path, bags: Path, names: tuple[str, str] = ("reference", "query")):
    ref, query = names
    doc = {
        "reference": ref,
        "datasets": {
            ref: {"source": str(bags / "reference")},
            query: {"source": str(bags / "query_1"), "inputs": QUERY_INPUTS},
        },
    }
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "pipeline.yaml").write_text(yaml.safe_dump(doc))


def last_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    """The one ``error:`` line, last on stderr (``sweep`` prints its plan first)."""
    err = capsys.readouterr().err.strip().splitlines()
    errors = [ln for ln in err if ln.startswith("error")]
    assert len(errors) == 1 and err[-1] == errors[0], err
    return errors[0]


@pytest.fixture(scope="module")
def bags(room_bags: Path) -> Path:
    return room_bags  # read, never written (the pipelines point at it)


@pytest.fixture(scope="module")
def done(tmp_path_factory: pytest.TempPathFactory, bags: Path) -> Path:
    """A project whose run finished (reference + one query): copied by the tests that need one."""
    project = tmp_path_factory.mktemp("done") / "p"
    write_pipeline(project, bags)
    run = tagtrail(project, "run")
    assert run.returncode == 0, run.stderr
    return project


@pytest.fixture
def project(done: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A copy of the finished project, the working directory."""
    copy = tmp_path / "p"
    shutil.copytree(done, copy, symlinks=True)
    monkeypatch.chdir(copy)
    return copy


@pytest.fixture
def victim(tmp_path: Path) -> Path:
    """A folder outside the project with a user's files (what a link might lead to)."""
    folder = tmp_path / "victim"
    (folder / "sub").mkdir(parents=True)
    (folder / "notes.txt").write_text("a user's notes\n")
    (folder / "sub" / "history").write_text("ls\n")
    (folder / ".env.override").write_text("X=1\n")
    return folder


def replace_with_link(path: Path, target: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.symlink_to(target)


# --- items 1 and 2: the symlink rule ---------------------------------------------------------


@pytest.mark.parametrize(
    "where",
    [
        "artifacts/tmp",
        "artifacts/runs",
        "artifacts/objects",
        "artifacts/objects/extract",
        "artifacts/logs",
        "artifacts/runs/query",
        "artifacts/sources.json",
        "artifacts/runs/reference/extract.json",
        "outputs/query",
        "outputs/reference/trajectory.csv",
    ],
)
def test_a_link_below_a_top_folder_leading_out_is_refused(project, victim, capsys, where):
    """Item 1 (``artifacts/tmp``, ``artifacts/runs``) and the rule at every level: refused with
    one line before anything is deleted or written, here or in the link's target."""
    target = victim / "notes.txt" if where.endswith((".json", ".csv")) else victim
    replace_with_link(project / where, target)
    before_victim, before_project = tree(victim), stamps(project)
    sweep = ["sweep", "-S", "smooth.pos_sigma_m=0.01,0.02"]
    for cmd in (["run"], ["run", "--force"], *([sweep] if where.startswith("artifacts") else [])):
        assert main(cmd) == 2, cmd
        line = last_error_line(capsys)
        assert "symlink leading outside" in line and where.split("/")[0] in line, line
        assert tree(victim) == before_victim
        assert stamps(project) == before_project  # nothing ran, nothing was written


def test_a_link_below_outputs_is_refused_before_any_stage_runs(
    bags, tmp_path, victim, monkeypatch, capsys
):
    """Item 2: ``outputs/query`` as a link was refused only after every stage ran."""
    project = tmp_path / "p"
    write_pipeline(project, bags)
    (project / "outputs").mkdir()
    (project / "outputs" / "query").symlink_to(victim)
    monkeypatch.chdir(project)
    before = tree(victim)
    assert main(["run"]) == 2
    assert "outputs/query is a symlink leading outside" in one_error_line(capsys)
    assert not (project / "artifacts").exists()  # no stage ran, no state written
    assert sorted(os.listdir(project / "outputs")) == ["query"]
    assert tree(victim) == before


@pytest.mark.parametrize(
    "where, target",
    [
        ("outputs/query", "missing"),  # dangling, inside outputs/
        ("outputs/query", "/nonexistent/q"),  # dangling, outside
        ("outputs/query", "../pipeline.yaml"),  # into the project, outside outputs/
        ("artifacts/objects", "../outputs"),  # into another top folder
    ],
)
def test_dangling_links_and_links_into_the_project_are_refused(project, capsys, where, target):
    replace_with_link(project / where, Path(target))
    before = stamps(project)
    assert main(["run"]) == 2
    assert "symlink" in one_error_line(capsys)
    assert stamps(project) == before


def test_a_top_folder_may_be_a_link_the_user_made(bags, tmp_path, monkeypatch, capsys):
    """Item 2: ``artifacts/`` (and ``outputs/``, ``sweeps/``) on a bigger disk is the project's
    own: run, sweep and export write there, and a rerun is all cached."""
    disk = tmp_path / "disk"
    project = tmp_path / "p"
    write_pipeline(project, bags)
    for top in ("artifacts", "outputs", "sweeps"):
        (disk / top).mkdir(parents=True)
        (project / top).symlink_to(disk / top)
    monkeypatch.chdir(project)
    assert main(["run"]) == 0
    assert (disk / "outputs" / "query" / "trajectory.csv").is_file()
    assert (disk / "artifacts" / "runs" / "last_run.json").is_file()
    assert main(["sweep", "-S", "smooth.pos_sigma_m=0.01,0.02", "--name", "s"]) == 0
    assert (disk / "sweeps" / "s" / "sweep.csv").is_file()
    capsys.readouterr()
    assert main(["run"]) == 0
    assert "0 ran" in capsys.readouterr().out
    assert all((project / top).is_symlink() for top in ("artifacts", "outputs", "sweeps"))


@pytest.mark.parametrize(
    "top, target, message",
    [
        ("artifacts", ".", "holds the project"),
        ("artifacts", "..", "holds the project"),
        ("artifacts", "outputs", "overlaps"),
        ("outputs", "artifacts/objects", "overlaps"),
        ("artifacts", "missing", "does not exist"),
        ("artifacts", "pipeline.yaml", "not a folder"),
    ],
)
def test_a_top_folder_link_must_lead_to_a_folder_of_its_own(project, capsys, top, target, message):
    shutil.rmtree(project / top)
    (project / top).symlink_to(target)
    before = stamps(project.parent)
    assert main(["run"]) == 2
    assert message in one_error_line(capsys)
    assert stamps(project.parent) == before


# --- item 3: only tagtrail's own files are removed --------------------------------------------

USER_FILES = {
    ".env.override": "X=1\n",
    ".vscode.settings": "{}\n",
    ".notes.20241203": "the user's notes\n",
    ".trajectory.csv.abcd1234": "mine\n",
}


def test_user_files_named_like_temp_files_are_never_removed(project, capsys):
    """Item 3: dotfiles ``.name.xxxxxxxx`` in ``outputs/<dataset>/`` and ``artifacts/`` survive
    every run; tagtrail's own stale temporary files (``.tagtrail-tmp-…``) are removed."""
    folders = [
        project / "outputs" / "reference",
        project / "artifacts",
        project / "artifacts" / "runs",
        project / "artifacts" / "runs" / "query",
    ]
    for folder in folders:
        for name, text in USER_FILES.items():
            (folder / name).write_text(text)
        (folder / ".tagtrail-tmp-trajectory.csv.k3j4h5g6").write_text("stale")
    (project / "artifacts" / "tmp" / "a-user-folder").mkdir()
    (project / "artifacts" / "tmp" / ".tagtrail-tmp-extract-0123456789ab-zz99yy88").mkdir()
    for cmd in (["run"], ["run", "--force"], ["run"]):
        assert main(cmd) == 0
    for folder in folders:
        assert {n: (folder / n).read_text() for n in USER_FILES} == USER_FILES
        assert not (folder / ".tagtrail-tmp-trajectory.csv.k3j4h5g6").exists()
    assert sorted(os.listdir(project / "artifacts" / "tmp")) == ["a-user-folder"]


def test_a_temp_file_being_written_is_never_removed(tmp_path: Path) -> None:
    """Clean-up takes only temporary files no process holds (a write in progress holds one)."""
    held = tmp_path / ".tagtrail-tmp-sources.json.a1b2c3d4"
    stale = tmp_path / ".tagtrail-tmp-sources.json.e5f6g7h8"
    held.write_text("{")
    stale.write_text("{")
    with open(held) as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        assert remove_stale_temps(tmp_path) == [stale]
    assert held.exists()
    atomic_write_text(tmp_path / "sources.json", "{}")  # a write removes its own stale temps
    assert sorted(os.listdir(tmp_path)) == ["sources.json"]


# --- item 6: read-only commands write nothing --------------------------------------------------


def test_read_only_commands_write_nothing(bags, tmp_path, project, monkeypatch, capsys):
    """Item 6: ``status`` on a fresh project created ``artifacts/sources.json``; ``show``
    rewrote it. Now status, dag, show and eval (without --csv) leave every file untouched."""
    fresh = tmp_path / "fresh"
    write_pipeline(fresh, bags)
    monkeypatch.chdir(fresh)
    for cmd in (["status"], ["dag"], ["run", "--dry-run"]):
        assert main(cmd) == 0, cmd
    assert sorted(os.listdir(fresh)) == ["pipeline.yaml"]
    monkeypatch.chdir(project)
    (project / "artifacts" / "sources.json").unlink()  # a project whose hashes were lost
    before = stamps(project)
    for cmd in (
        ["status"],
        ["dag"],
        ["show", "smooth"],
        ["show", "pnp", "--dataset", "query"],
        ["eval"],
        ["run", "--dry-run"],
    ):
        assert main(cmd) == 0, cmd
        assert stamps(project) == before, cmd


def test_a_source_that_is_no_recording_is_refused_at_once(tmp_path, monkeypatch, capsys):
    """Item 6: ``source: /usr`` was hashed for 46 s (a 20 MB sources.json); now one line."""
    (tmp_path / "pipeline.yaml").write_text(
        yaml.safe_dump({"reference": "r", "datasets": {"r": {"source": "/usr"}}})
    )
    monkeypatch.chdir(tmp_path)
    for cmd in (["status"], ["run"]):
        t0 = time.perf_counter()
        assert main(cmd) == 2
        assert time.perf_counter() - t0 < 5
        assert "/usr: empty or unrecognised source folder" in one_error_line(capsys)
    assert not (tmp_path / "artifacts" / "sources.json").exists()


# --- item 8: two runs at once ------------------------------------------------------------------


@pytest.mark.slow
def test_two_runs_at_once_both_succeed(bags, tmp_path) -> None:
    """Item 8: the first of two simultaneous runs failed 3 times in 4 with ``FileNotFoundError:
    …/.sources.json.XXXX`` (state written after the lock was released; the other run's clean-up
    removed the temporary file). Here the first run pauses 8 s with ``sources.json`` written but
    not yet in place and the second starts then, which made the first fail every time; now the
    first holds the lock while it writes its state and the second waits."""
    project = tmp_path / "p"
    write_pipeline(project, bags)
    env = {k: v for k, v in os.environ.items() if k != "TAGTRAIL_FAULT"}
    cmd = [sys.executable, "-m", "tagtrail.cli", "run", "extract"]
    pause = {**env, "TAGTRAIL_FAULT": "sleep@written:sources.json=8"}
    first = subprocess.Popen(
        cmd, cwd=project, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=pause
    )
    deadline = time.monotonic() + 120
    while not list(project.glob("artifacts/.*sources.json.*")) and time.monotonic() < deadline:
        time.sleep(0.02)  # the first run is writing its state
    second = subprocess.Popen(
        cmd, cwd=project, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )
    results = [(p.returncode, err) for p in (first, second) for _, err in [p.communicate(300)]]
    assert [rc for rc, _ in results] == [0, 0], results
    assert "waiting for another tagtrail run" in results[1][1]
    assert (project / "artifacts" / "sources.json").is_file()
    assert list((project / "artifacts").rglob(".tagtrail-tmp-*")) == []


# --- item 12: a path in the way of an output ---------------------------------------------------


def test_an_empty_folder_or_file_in_the_way_is_replaced(project, done, capsys):
    """Item 12: ``trajectory.csv`` replaced by a folder, or ``outputs/query`` by a file, gave
    ``IsADirectoryError`` / ``FileExistsError``; empty ones are now replaced and restored."""
    good = tree(done / "outputs")
    (project / "outputs" / "reference" / "trajectory.csv").unlink()
    (project / "outputs" / "reference" / "trajectory.csv").mkdir()
    shutil.rmtree(project / "outputs" / "query")
    (project / "outputs" / "query").touch()
    (project / "artifacts" / "runs" / "query" / "smooth.json").unlink()
    (project / "artifacts" / "runs" / "query" / "smooth.json").mkdir()
    assert main(["run"]) == 0
    assert tree(project / "outputs") == good
    assert not (project / "artifacts" / "runs" / "query" / "smooth.json").is_dir()
    assert main(["run", "smooth", "--force"]) == 0
    assert (project / "artifacts" / "runs" / "query" / "smooth.json").is_file()


@pytest.mark.parametrize(
    "where",
    [
        "outputs/reference/trajectory.csv",
        "outputs/query",
        "artifacts/runs/query/smooth.json",
        "artifacts/objects",
    ],
)
def test_a_users_file_or_folder_in_the_way_is_refused(project, capsys, where):
    """Item 12: what is in the way holds something (the user's): one line, nothing touched."""
    path = project / where
    shutil.rmtree(path) if path.is_dir() else path.unlink()
    if path.suffix in (".csv", ".json"):
        path.mkdir()
        (path / "keep.txt").write_text("mine\n")
    else:
        path.write_text("mine\n")
    before = stamps(project)
    assert main(["run", "--force"]) == 2
    line = one_error_line(capsys)
    assert f"{where} is a" in line and "not empty" in line, line
    assert stamps(project) == before


# --- item 13 (part): dataset names that collide or are too long -------------------------------


@pytest.mark.parametrize(
    "name, message",
    [
        ("last_run.json", "tagtrail names its own files so"),
        (".tagtrail-export.json", "tagtrail names its own files so"),
        ("q" * 300, "300 characters, at most 100"),
    ],
)
def test_a_dataset_name_tagtrail_cannot_use_is_refused_at_load(
    bags, tmp_path, monkeypatch, capsys, name, message
):
    write_pipeline(tmp_path, bags, names=("reference", name))
    monkeypatch.chdir(tmp_path)
    for cmd in (["run"], ["status"], ["dag"]):
        assert main(cmd) == 2
        line = one_error_line(capsys)
        assert "is not allowed" in line and message in line and len(line) < 400, line
    assert sorted(os.listdir(tmp_path)) == ["pipeline.yaml"]


# --- item 15: a killed export-mcap --------------------------------------------------------------


def test_a_killed_export_mcap_leaves_no_temp_after_the_next(project) -> None:
    """Item 15: SIGKILL during ``export-mcap -o k.mcap`` left ``.k.mcap.XXXX`` for good; the
    next export to that path removes its own stale temporary file (and nothing else)."""
    (project / ".k.mcap.notmine1").write_text("a user's file")
    killed = tagtrail(project, "export-mcap", "-o", "k.mcap", fault="kill@write:k.mcap")
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert [p.name for p in project.glob(".tagtrail-tmp-k.mcap.*")] != []
    ok = tagtrail(project, "export-mcap", "-o", "k.mcap")
    assert ok.returncode == 0, ok.stderr
    assert list(project.glob(".tagtrail-tmp-*")) == []
    assert (project / "k.mcap").stat().st_size > 0
    assert (project / ".k.mcap.notmine1").read_text() == "a user's file"


def test_output_files_list_is_what_the_exporters_write(done: Path) -> None:
    """The list the paths are checked against names every file an export writes."""
    written = {p.name for p in (done / "outputs").rglob("*") if p.is_file()}
    assert written <= set(OUTPUT_FILES)


def test_demo_refuses_a_link_out_before_any_stage_runs(tmp_path, victim, monkeypatch, capsys):
    """Probe: ``demo --dir`` (run + export in one command) checked outputs/ only after the
    stages ran; now before."""
    demo = tmp_path / "demo"
    (demo / "outputs").mkdir(parents=True)
    (demo / "outputs" / "reference").symlink_to(victim)
    before = tree(victim)
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--dir", str(demo), "--frames", "30"]) == 2
    assert "outputs/reference is a symlink leading outside" in last_error_line(capsys)
    assert not (demo / "artifacts").exists()
    assert tree(victim) == before

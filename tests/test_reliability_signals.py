"""Reliability, round two (issue 26): a signal ends any command within a second with one line,
and a bad value is one ``error:`` line at load.

Signals: ``tagtrail`` runs as a real subprocess in its own session and gets a real signal, the
way a terminal's Ctrl-C reaches it (the whole foreground group), at a real moment: while the
detector workers of extract run on a real bag, while a sweep runs its points, or at a named
point (``TAGTRAIL_FAULT=SIGINT@<point>``, ``tagtrail/faults.py``: the process signals itself
there). Each must end within a second, exit 130 (SIGTERM 143, SIGHUP 129) with the one line
``interrupted`` (``interrupted by SIGTERM``), and the next run must give outputs byte-identical
to an undisturbed run's.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tagtrail.sim import simulate
from tests.cli_helpers import detection_bags

REPO = Path(__file__).resolve().parents[1]
STOP_S = 1.0  # the promise: a signal ends any command within a second
TEMP = re.compile(r"^\..+\.[a-z0-9_]{8}$")  # mkstemp's names


def env(fault: str | None = None) -> dict[str, str]:
    out = {k: v for k, v in os.environ.items() if k != "TAGTRAIL_FAULT"}
    out["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [out.get("PYTHONPATH")])])
    if fault:
        out["TAGTRAIL_FAULT"] = fault
    return out


def tagtrail(cwd: Path, *args: str, fault: str | None = None,
             timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "tagtrail.cli", *args], cwd=cwd,
                          env=env(fault), capture_output=True, text=True, timeout=timeout)


def start(cwd: Path, *args: str) -> subprocess.Popen[str]:
    """``tagtrail ARGS`` in a session of its own: its process group is what Ctrl-C signals."""
    return subprocess.Popen([sys.executable, "-m", "tagtrail.cli", *args], cwd=cwd, env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*/children"):
        out += [int(c) for c in task.read_text().split()]
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def detector_workers(pid: int, timeout: float = 120) -> list[int]:
    """The detector worker processes of ``pid``, once extract has started them."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = [c for c in children(pid) if "tagtrail.pool" in cmdline(c)]
        if found:
            return found
        time.sleep(0.02)
    raise AssertionError("extract never started its detector workers")


def alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def interrupt(proc: subprocess.Popen[str], sig: int = signal.SIGINT) -> tuple[float, str, str]:
    """Signal ``proc``'s group as a terminal does; (seconds until it ended, stdout, stderr)."""
    t0 = time.monotonic()
    os.killpg(proc.pid, sig)
    while proc.poll() is None and time.monotonic() - t0 < 30:
        time.sleep(0.005)
    took = time.monotonic() - t0
    out, err = proc.communicate(timeout=30)
    return took, out, err


def check_one_line(rc: int, err: str, sig: int = signal.SIGINT) -> None:
    """Exit 128 + n and, after whatever progress the command printed, one line saying so."""
    line = "interrupted" if sig == signal.SIGINT else f"interrupted by {signal.Signals(sig).name}"
    lines = err.strip().splitlines()
    assert rc == 128 + sig, err
    assert lines and lines[-1] == line, err
    assert sum(ln.startswith("interrupted") for ln in lines) == 1, err
    assert "Traceback" not in err and "error:" not in err, err


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


def stray(project: Path) -> list[str]:
    left = [str(p.relative_to(project)) for p in project.rglob("*") if TEMP.match(p.name)]
    tmp = project / "artifacts" / "tmp"
    return left + ([str(p) for p in tmp.iterdir()] if tmp.is_dir() else [])


def new_project(folder: Path, bags: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    doc = {"reference": "reference", "datasets": {
        "reference": {"source": str(bags / "reference")},
        "query": {"source": str(bags / "query_1")}}}
    (folder / "pipeline.yaml").write_text(yaml.safe_dump(doc))
    return folder


@pytest.fixture(scope="module")
def images(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real image recording whose extract takes seconds (rendered room, 120 frames)."""
    root = tmp_path_factory.mktemp("images")
    simulate("room", root, compressed=True, frames=120, query_frames=8)
    return root


@pytest.fixture(scope="module")
def images_good(tmp_path_factory: pytest.TempPathFactory, images: Path) -> dict[str, bytes]:
    project = new_project(tmp_path_factory.mktemp("images_good"), images)
    done = tagtrail(project, "run")
    assert done.returncode == 0, done.stderr
    return files(project / "outputs")


@pytest.fixture(scope="module")
def dets(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return detection_bags(tmp_path_factory.mktemp("dets"))


@pytest.fixture(scope="module")
def dets_good(tmp_path_factory: pytest.TempPathFactory, dets: Path) -> dict[str, bytes]:
    project = new_project(tmp_path_factory.mktemp("dets_good"), dets)
    done = tagtrail(project, "run")
    assert done.returncode == 0, done.stderr
    return files(project / "outputs")


# --- 9. Ctrl-C during extract ----------------------------------------------------------------

@pytest.mark.parametrize("jobs", ["1", "2"])
def test_ctrl_c_during_extract_ends_within_a_second(images, images_good, tmp_path, jobs):
    """Was: rc 1, ``stage extract failed: KeyboardInterrupt`` and a log file."""
    project = new_project(tmp_path / "p", images)
    proc = start(project, "run", "-j", jobs)
    workers = detector_workers(proc.pid)
    time.sleep(0.3)  # detecting frames
    took, out, err = interrupt(proc)
    check_one_line(proc.returncode, err)
    assert took < STOP_S, f"{took:.2f} s"
    assert "extract [reference]" not in out  # it was interrupted, neither ran nor failed
    assert not list((project / "artifacts" / "logs").glob("*")), "a stage failure was logged"
    deadline = time.monotonic() + STOP_S
    while any(alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not any(alive(w) for w in workers), "detector workers outlived the command"
    again = tagtrail(project, "run")
    assert again.returncode == 0, again.stderr
    assert files(project / "outputs") == images_good
    assert stray(project) == []


# --- 9 (class). A signal at any point of a run ------------------------------------------------

@pytest.mark.parametrize("fault", [
    "SIGINT@stage:extract",  # extract computed, not stored
    "SIGINT@store:optimize",  # inside the store's write
    "SIGINT@export:tag_map",  # exporting the outputs
    "SIGINT@write:last_run.json",  # the run log, the run's last write
    "SIGINT@cli:exit",  # the command finished (was: rc -2, no message)
    "SIGTERM@stage:pnp",
    "SIGHUP@store:trajectory",
])
def test_signal_at_any_point_of_a_run(dets, dets_good, tmp_path, fault):
    project = new_project(tmp_path / "p", dets)
    t0 = time.monotonic()
    hit = tagtrail(project, "run", fault=fault)
    sig = getattr(signal, fault.split("@")[0])
    check_one_line(hit.returncode, hit.stderr, sig)
    assert not list((project / "artifacts" / "logs").glob("*")), hit.stderr
    again = tagtrail(project, "run")
    assert again.returncode == 0, again.stderr
    assert files(project / "outputs") == dets_good
    assert stray(project) == []
    assert time.monotonic() - t0 < 300


# --- 5. Ctrl-C stops a sweep ------------------------------------------------------------------

def metrics(table: Path) -> list[dict[str, str]]:
    """sweep.csv's parameter and metric columns (not its timings)."""
    import csv

    with table.open() as f:
        rows = list(csv.DictReader(f))
    return [{k: v for k, v in r.items() if k in ("point", "status", "best") or "[" in k
             or k.startswith("optimize.")} for r in rows]


def test_ctrl_c_stops_a_sweep(dets, tmp_path):
    """Was: the running point marked ``failed: KeyboardInterrupt``, the others run on (rc 1); a
    1,000-point sweep had not stopped 60 s after SIGINT."""
    project = new_project(tmp_path / "p", dets)
    values = [f"{0.05 + 0.001 * i:.3f}" for i in range(300)]
    proc = start(project, "sweep", "-S", "optimize.f_scale=" + ",".join(values), "--name", "big")
    assert proc.stderr is not None
    seen = []
    for line in proc.stderr:  # the progress lines; signal once the second point has started
        seen.append(line)
        if "point 2/300" in line:
            break
    else:
        raise AssertionError("".join(seen))
    took, _, err = interrupt(proc)
    check_one_line(proc.returncode, "".join(seen) + err)
    assert took < STOP_S, f"{took:.2f} s"
    rows = metrics(project / "sweeps" / "big" / "sweep.csv")
    assert 1 <= len(rows) <= 2 and all(r["status"] == "ok" for r in rows), rows
    # what the interrupted sweep left in the cache gives the same numbers as a fresh project
    few = ["-S", "optimize.f_scale=" + ",".join(values[:3]), "--name", "few"]
    resumed = tagtrail(project, "sweep", *few)
    assert resumed.returncode == 0, resumed.stderr
    fresh_project = new_project(tmp_path / "fresh", dets)
    fresh = tagtrail(fresh_project, "sweep", *few)
    assert fresh.returncode == 0, fresh.stderr
    assert metrics(project / "sweeps" / "few" / "sweep.csv") == metrics(
        fresh_project / "sweeps" / "few" / "sweep.csv")


# --- 9 (class). Other commands ----------------------------------------------------------------

def test_ctrl_c_during_simulate_and_demo(tmp_path):
    """Rendering recordings (simulate, and demo's first step): 130 and one line within a
    second; rendering again from scratch (``--force``) then succeeds."""
    for args, marker in ((["simulate", "room", "-o", "sim", "--frames", "400", "--no-progress"],
                          tmp_path / "sim"),
                         (["demo", "--dir", "demo"], tmp_path / "demo")):
        proc = start(tmp_path, *args)
        deadline = time.monotonic() + 120
        while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.5)
        assert proc.poll() is None, proc.communicate()
        took, _, err = interrupt(proc)
        check_one_line(proc.returncode, err)
        assert took < STOP_S, (args[0], took)
    again = tagtrail(tmp_path, "simulate", "room", "-o", "sim", "--frames", "20", "--force",
                     "--no-progress", "--query-frames", "3")
    assert again.returncode == 0, again.stderr


@pytest.mark.parametrize("command", ["init", "eval", "relocalize", "export-mcap", "show"])
def test_ctrl_c_in_other_commands(dets, tmp_path, command):
    """At each command's own write (or, for ``show``, when it is done): 130 and one line, and
    the file it was writing is not left half-written (absent, its temp file removed)."""
    project = new_project(tmp_path / "p", dets)
    assert tagtrail(project, "run").returncode == 0
    args, target = {
        "init": (["init", "--reference", str(dets / "reference"), "-o", "new.yaml"], "new.yaml"),
        "eval": (["eval", "--csv", "eval.csv"], "eval.csv"),
        "relocalize": (["relocalize", "outputs/reference", "outputs/query", "-o", "reloc"],
                       "reloc/relocalization.csv"),
        "export-mcap": (["export-mcap", "-o", "run.mcap"], "run.mcap"),
        "show": (["show", "optimize"], None),
    }[command]
    fault = f"SIGINT@write:{Path(target).name}" if target else "SIGINT@cli:exit"
    hit = tagtrail(project, *args, fault=fault)
    check_one_line(hit.returncode, hit.stderr)
    if target:
        assert not (project / target).exists(), f"{target} written although interrupted"
    assert stray(project) == []
    assert tagtrail(project, *args).returncode == 0

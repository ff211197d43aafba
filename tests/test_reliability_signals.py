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
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tagtrail.sim import simulate
from tests.cli_helpers import alive, children, cli_env, files, stray, tagtrail, terminal_signals

pytestmark = pytest.mark.slow  # signals sent to real runs at every point (make test-all)

STOP_S = 1.0  # the promise: a signal ends any command within a second


def start(cwd: Path, *args: str) -> subprocess.Popen[str]:
    """``tagtrail ARGS`` in a session of its own: its process group is what Ctrl-C signals."""
    return subprocess.Popen(
        [sys.executable, "-m", "tagtrail.cli", *args],
        cwd=cwd,
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=terminal_signals,
    )


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


def new_project(folder: Path, bags: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    doc = {
        "reference": "reference",
        "datasets": {
            "reference": {"source": str(bags / "reference")},
            "query": {"source": str(bags / "query_1")},
        },
    }
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
def dets(room_bags: Path) -> Path:
    return room_bags


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


@pytest.mark.parametrize(
    "fault",
    [
        "SIGINT@stage:extract",  # extract computed, not stored
        "SIGINT@store:optimize",  # inside the store's write
        "SIGINT@export:tag_map",  # exporting the outputs
        "SIGINT@write:last_run.json",  # the run log, the run's last write
        "SIGINT@cli:exit",  # the command finished (was: rc -2, no message)
        "SIGTERM@stage:pnp",
        "SIGHUP@store:trajectory",
    ],
)
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
    return [
        {
            k: v
            for k, v in r.items()
            if k in ("point", "status", "best") or "[" in k or k.startswith("optimize.")
        }
        for r in rows
    ]


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
        fresh_project / "sweeps" / "few" / "sweep.csv"
    )


# --- 9 (class). Other commands ----------------------------------------------------------------


def test_ctrl_c_during_simulate_and_demo(tmp_path):
    """Rendering recordings (simulate, and demo's first step): 130 and one line within a
    second; rendering again from scratch (``--force``) then succeeds."""
    for args, marker in (
        (["simulate", "room", "-o", "sim", "--frames", "400", "--no-progress"], tmp_path / "sim"),
        (["demo", "--dir", "demo"], tmp_path / "demo"),
    ):
        proc = start(tmp_path, *args)
        deadline = time.monotonic() + 120
        while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.5)
        assert proc.poll() is None, proc.communicate()
        took, _, err = interrupt(proc)
        check_one_line(proc.returncode, err)
        assert took < STOP_S, (args[0], took)
    again = tagtrail(
        tmp_path,
        "simulate",
        "room",
        "-o",
        "sim",
        "--frames",
        "20",
        "--force",
        "--no-progress",
        "--query-frames",
        "3",
    )
    assert again.returncode == 0, again.stderr


@pytest.mark.parametrize("command", ["init", "eval", "relocalize", "export-mcap", "show"])
def test_ctrl_c_in_other_commands(dets, tmp_path, command):
    """At each command's own write (or, for ``show``, when it is done): 130 and one line, and
    the file it was writing is not left half-written (absent, its temp file removed)."""
    project = new_project(tmp_path / "p", dets)
    assert tagtrail(project, "run").returncode == 0
    args, target = {
        "init": (
            [
                "init",
                "--reference",
                str(dets / "reference"),
                "--tag-size",
                "0.16",
                "-o",
                "new.yaml",
            ],
            "new.yaml",
        ),
        "eval": (["eval", "--csv", "eval.csv"], "eval.csv"),
        "relocalize": (
            ["relocalize", "outputs/reference", "outputs/query", "-o", "reloc"],
            "reloc/relocalization.csv",
        ),
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


# --- 11, 13. Every parameter has a range, checked at load -------------------------------------


def _bounded(annotation: object, metadata: list[object], where: str, found: list[str]) -> None:
    """Walk a field's type: every int/float leaf needs a lower and an upper bound (its own
    ``Annotated`` metadata, or the field's when the leaf is the field itself)."""
    import types
    import typing

    import annotated_types as at
    from pydantic import BaseModel
    from pydantic.fields import FieldInfo

    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        base, *meta = typing.get_args(annotation)
        flat = [x for m in meta for x in (m.metadata if isinstance(m, FieldInfo) else [m])]
        _bounded(base, [*metadata, *flat], where, found)
        return
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(annotation):
            _bounded(arg, metadata, where, found)
        return
    if origin in (tuple, list, dict):
        for arg in typing.get_args(annotation):
            if arg is not Ellipsis:
                _bounded(arg, [], where, found)  # container items: their own bounds
        return
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        for name, f in annotation.model_fields.items():
            _bounded(f.annotation, list(f.metadata), f"{where}.{name}", found)
        return
    if annotation in (int, float):
        low = any(isinstance(m, at.Ge | at.Gt) for m in metadata)
        high = any(isinstance(m, at.Le | at.Lt) for m in metadata)
        if not (low and high):
            found.append(
                f"{where} ({annotation.__name__}: {'no lower ' if not low else ''}"
                f"{'no upper ' if not high else ''}bound)"
            )


def numeric_fields() -> list[tuple[str, str]]:
    from tagtrail.stages import REGISTRY

    out = []
    for stage, module in REGISTRY.items():
        for name, f in module.Params.model_fields.items():
            text = str(f.annotation)
            if ("int" in text or "float" in text) and "Config" not in text:  # a number here
                out.append((stage, name))
    return out


def test_every_numeric_parameter_has_a_finite_range() -> None:
    """Walks every stage's Params (nested models, tuples, dicts): a new number without a range
    fails here."""
    from tagtrail.schemas.pipeline import KnownTag, SurveyConfig, TagSizesFile
    from tagtrail.stages import REGISTRY

    missing: list[str] = []
    for stage, module in REGISTRY.items():
        for name, f in module.Params.model_fields.items():
            _bounded(f.annotation, list(f.metadata), f"{stage}.{name}", missing)
    for model in (KnownTag, SurveyConfig, TagSizesFile):
        _bounded(model, [], model.__name__, missing)
    assert not missing, "parameters without a range:\n" + "\n".join(missing)
    assert len(numeric_fields()) >= 40  # the walk saw the numbers (not an empty registry)


@pytest.fixture
def project(dets, tmp_path, monkeypatch) -> Path:
    monkeypatch.chdir(new_project(tmp_path / "p", dets))
    return tmp_path / "p"


@pytest.mark.parametrize(("stage", "param"), numeric_fields())
def test_out_of_range_override_is_one_line_naming_s(project, capsys, stage, param) -> None:
    """``-S stage.param=1e300`` (and -1e300): exit 2, one ``error:`` line naming the -S, at load
    (``dag`` runs nothing). Was: a segfault in the detector (extract.quad_decimate=300),
    LinAlgError in optimize (pnp.tag_size=1e300)."""
    from tagtrail.cli import main
    from tagtrail.stages import REGISTRY

    f = REGISTRY[stage].Params.model_fields[param]
    text = str(f.annotation)
    if "tuple" in text and "int" in text:
        values = ["[10000000000]", "[-1]"]
    elif "tuple" in text:
        values = ["[1e300, 1e300]", "[-1e300, 1]"]
    elif "dict" in text:
        values = ["{1: 1e300}", "{-1: 0.1}"]
    else:
        values = ["1e300", "-1e300"] if "float" in text else ["10000000000", "-10000000000"]
    for value in values:
        assert main(["dag", "-S", f"{stage}.{param}={value}"]) == 2, value
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"error: -S {stage}.{param}="), err
        assert len(err[0]) < 300, err


def test_quad_decimate_300_and_tag_size_1e300(project) -> None:
    """The issue's own cases through the real command, as a subprocess (no worker crash)."""
    for s in ("extract.quad_decimate=300", "extract.quad_decimate=1e9", "pnp.tag_size=1e300"):
        done = tagtrail(project, "run", "-S", s)
        assert done.returncode == 2, done.stderr
        assert done.stderr.startswith(f"error: -S {s}: ") and done.stderr.count("\n") == 1
    assert not (project / "artifacts" / "objects").exists()  # refused before any work


def test_out_of_range_in_the_pipeline_file_names_the_file(project, capsys) -> None:
    from tagtrail.cli import main

    doc = yaml.safe_load((project / "pipeline.yaml").read_text())
    doc["stages"] = {"optimize": {"joint": {"corner_sigma_px": 1e-300}}}
    (project / "pipeline.yaml").write_text(yaml.safe_dump(doc))
    assert main(["status"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: pipeline.yaml: stages.optimize.joint.corner_sigma_px: "), err


# --- 10. YAML alias bombs, bounded messages ---------------------------------------------------


def bomb(levels: int) -> str:
    lines = [
        "reference: reference",
        "datasets:",
        "  reference: {source: bags}",
        "x0: &x0 [0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1]",
    ]
    lines += [f"x{i}: &x{i} [{', '.join([f'*x{i - 1}'] * 9)}]" for i in range(1, levels)]
    return (
        "\n".join(
            [
                *lines[:3],
                "stages:",
                f"  pnp: {{tag_size: *x{levels - 1}}}",
                "anchors:",
                *("  " + ln for ln in lines[3:]),
            ]
        )
        + "\n"
    )


@pytest.mark.parametrize("levels", [6, 7, 9])
def test_yaml_alias_bomb_is_refused_fast_in_one_short_line(project, capsys, levels) -> None:
    """Was: 9 levels ``unexpected MemoryError`` after 56 s; 7 levels a 58 MB ``error:`` line."""
    from tagtrail.cli import main

    text = bomb(levels)
    assert len(text) < 1000
    (project / "pipeline.yaml").write_text(text)
    t0 = time.monotonic()
    assert main(["status"]) == 2
    took = time.monotonic() - t0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: pipeline.yaml: "), err
    assert len(err[0]) < 300, len(err[0])
    assert took < 5.0, took
    if 9**levels > 1_000_000:
        assert "alias" in err[0], err


@pytest.mark.parametrize(
    "text",
    [
        "a: &a [*a]\n",  # a recursive alias
        "x: " + "[" * 5000 + "]" * 5000 + "\n",  # nested too deeply
    ],
)
def test_yaml_recursion_is_refused(project, capsys, text) -> None:
    from tagtrail.cli import main

    (project / "pipeline.yaml").write_text(text)
    assert main(["status"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: pipeline.yaml: "), err


@pytest.mark.parametrize(
    "value", ["[" + ", ".join(["0.1"] * 200_000) + "]", "[" * 3000 + "]" * 3000]
)
def test_a_huge_value_in_an_error_is_abbreviated(project, capsys, value) -> None:
    from tagtrail.cli import main

    assert main(["dag", "-S", f"pnp.tag_size={value}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and len(err[0]) < 400, err[0][:500]


# --- 13. Wiring an artifact of the wrong kind; simulate --size --------------------------------


@pytest.mark.parametrize(
    ("key", "ref", "says"),
    [
        ("trajectory.tag_map", "reference:pnp.observations", "takes a tag_map artifact"),
        ("align.tag_map", "reference:optimize.report", "takes a tag_map artifact"),
        ("trajectory.tag_map", "reference:optimize.tagmap", "has no output 'tagmap'"),
        ("trajectory.tag_map", "source", "takes optimize.tag_map only"),
    ],
)
def test_input_of_the_wrong_kind_is_refused_at_load(project, capsys, key, ref, says) -> None:
    """Was: ``KeyError: 'tag_id'`` deep in trajectory, rc 1."""
    from tagtrail.cli import main

    doc = yaml.safe_load((project / "pipeline.yaml").read_text())
    doc["datasets"]["query"]["inputs"] = {key: ref}
    (project / "pipeline.yaml").write_text(yaml.safe_dump(doc))
    assert main(["run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"datasets.query.inputs: {key}" in err[0] and says in err[0], err
    assert not (project / "artifacts" / "objects").exists()


@pytest.mark.parametrize(
    "args",
    [
        ["--size", "20000x20000"],
        ["--frames", "0"],
        ["--fps", "nan"],
        ["--tag-size", "1e300"],
        ["--tag-sizes", "1=1e300"],
    ],
)
def test_simulate_absurd_sizes_are_one_line(tmp_path, capsys, args) -> None:
    """Was: ``simulate --size 20000x20000``: ``MemoryError``."""
    from tagtrail.cli import main

    assert main(["simulate", "room", "-o", str(tmp_path / "sim"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {args[0]}: "), err
    assert not (tmp_path / "sim").exists()


GC_CHILD = """
import gc, sys, time
from tagtrail import signals

def slow_callback(phase, info):  # as dask's distributed registers one
    if phase == "start":
        print("in-gc", flush=True)
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            pass

signals.install()
gc.callbacks.append(slow_callback)
try:
    while True:
        gc.collect()
        end = time.monotonic() + 0.05  # the program's own work between collections
        while time.monotonic() < end:
            pass
except KeyboardInterrupt as err:
    print("unwound", flush=True)
    signals.finish(signals.report(err))
"""


def test_a_signal_inside_a_gc_callback_still_unwinds_the_command() -> None:
    """A signal that lands while the garbage collector runs a callback (where a raised
    exception is printed as "Exception ignored" and dropped) unwinds the command all the same,
    its one line and nothing else on stderr. The child spends 6/7 of its time in the callback
    and the rest computing: the signal, delivered again every few ms until it lands outside a
    callback, lands in that work. (A child calling ``gc.collect`` back to back left a window of
    a few bytecodes between callbacks: the signal found it after 0.4-16 s, or not within 30.)"""
    proc = subprocess.Popen(
        [sys.executable, "-c", GC_CHILD],
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=terminal_signals,
    )
    assert proc.stdout is not None
    try:
        assert proc.stdout.readline() == "in-gc\n"
        proc.send_signal(signal.SIGINT)  # inside the callback's 0.3 s
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:  # a failure must not leave the child spinning
            proc.kill()
            proc.wait()
    assert "unwound" in out, (out, err)
    assert proc.returncode == 130 and err.strip() == "interrupted", err

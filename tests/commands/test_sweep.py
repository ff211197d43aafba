"""``tagtrail sweep`` on the simulator's `room` recordings (the demo pipeline): a 3×3 optimize grid
runs extract once (read from the sweep's run log and the store), ``sweep.csv`` holds a row per
point with the metrics the artifacts hold, a sweep killed mid-way (between points, and inside a
stage) resumes without redoing finished points, ``show --point`` opens a point's artifacts, and
bad input is one error line."""

from __future__ import annotations

import importlib.util
import json
import re
import signal
from pathlib import Path
from typing import Any

import pytest

import tagtrail.cli
from tagtrail.commands import sweep as sweep_cmd
from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.runner.sweep import (
    make_points,
    read_table,
    split_values,
    within_noise,
    yaml_text,
)
from tagtrail.sim import simulate
from tagtrail.stages import REGISTRY
from tests.cli_helpers import TEMP, demo_project, one_error_line
from tests.cli_helpers import tagtrail as cli

Capsys = pytest.CaptureFixture[str]
GRID = ["-S", "optimize.loss=linear,soft_l1,huber", "-S", "optimize.f_scale=0.05,0.1,0.2"]
NAME = "optimize.loss-optimize.f_scale"
DATASETS = ["reference", "query_1", "query_2", "query_3"]
FIRST = "trajectory.rmse_m[reference]"
KEY = re.compile(r"^[0-9a-f]{64}$")


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The room detections with a 60-frame reference: its points' D differ beyond the noise
    (on room_bags' 40 frames no point is "best")."""
    root = tmp_path_factory.mktemp("room")
    simulate("room", root, frames=60, query_frames=5, detections=True)
    return root


def sweep(project: Path, capsys: Capsys, *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = sweep_cmd.main(["-p", str(project / "pipeline.yaml"), *argv])
    out, err = capsys.readouterr()
    return rc, out, err


def run_log(project: Path, name: str = NAME) -> list[dict[str, Any]]:
    doc: list[dict[str, Any]] = json.loads((project / "sweeps" / name / "runs.json").read_text())
    return doc


def ran(log: list[dict[str, Any]], stage: str | None = None) -> dict[int, list[str]]:
    """Point → the nodes (``stage [dataset]``) it ran, in this invocation."""
    return {
        p["point"]: [
            f"{n['stage']} [{n['dataset']}]"
            for n in p["nodes"]
            if n["status"] == "ran" and stage in (None, n["stage"])
        ]
        for p in log
    }


def table(project: Path, name: str = NAME) -> list[dict[str, str]]:
    return read_table(project / "sweeps" / name / "sweep.csv")


def strip(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """The rows without what depends on the invocation (its wall time, what it ran)."""
    return [{k: v for k, v in r.items() if k not in ("wall_s", "ran", "cached")} for r in rows]


@pytest.fixture(scope="module")
def swept(tmp_path_factory: pytest.TempPathFactory, data: Path) -> tuple[Path, str, str]:
    """A fresh project (nothing cached) after the 3×3 optimize sweep; its stdout and stderr.
    Its run log is kept as ``runs.first.json`` (later tests sweep again)."""
    project = demo_project(tmp_path_factory.mktemp("sweep"), data)
    out = cli(project, "sweep", *GRID)
    assert out.returncode == 0, out.stderr
    folder = project / "sweeps" / NAME
    (folder / "runs.first.json").write_text((folder / "runs.json").read_text())
    return project, out.stdout, out.stderr


def test_a_3x3_optimize_sweep_runs_extract_once(swept: tuple[Path, str, str]) -> None:
    project, _, _ = swept
    log = json.loads((project / "sweeps" / NAME / "runs.first.json").read_text())
    assert [p["point"] for p in log] == list(range(1, 10))
    extract = ran(log, "extract")
    assert sorted(extract[1]) == sorted(f"extract [{d}]" for d in DATASETS)
    assert all(extract[p] == [] for p in range(2, 10))
    for stage in ("pnp", "edges"):  # nor anything else upstream of optimize
        assert all(ran(log, stage)[p] == [] for p in range(2, 10))
    assert all(ran(log, "optimize")[p] for p in range(1, 10))  # every point fits its own map
    # The store agrees: one extract entry per dataset, ever; the last point's run log (the
    # runner's own) found extract cached.
    assert len(list((project / "artifacts" / "objects" / "extract").iterdir())) == len(DATASETS)
    last = json.loads((project / "artifacts" / "runs" / "last_run.json").read_text())
    assert {n["status"] for n in last if n["stage"] == "extract"} == {"cached"}


def test_sweep_csv_has_a_row_per_point_with_metrics_and_keys(swept: tuple[Path, str, str]) -> None:
    project, out, err = swept
    rows = table(project)
    assert len(rows) == 9
    grid = [(loss, fs) for loss in ("linear", "soft_l1", "huber") for fs in ("0.05", "0.1", "0.2")]
    assert [(r["optimize.loss"], r["optimize.f_scale"]) for r in rows] == grid
    assert [r["point"] for r in rows] == [str(i) for i in range(1, 10)]
    metrics = [
        FIRST,
        "tags.rmse_m[reference]",
        "map.rms_t_m[reference]",
        *(f"D.mean_m[{d}]" for d in DATASETS[1:]),
        *(f"abs_phi.mean_deg[{d}]" for d in DATASETS[1:]),
    ]
    for r in rows:
        assert r["status"] == "ok"
        for m in metrics:
            assert float(r[m]) >= 0.0, (m, r[m])
        assert float(r["time_s.extract"]) > 0 and float(r["time_s.optimize"]) > 0
        keys = {c: v for c, v in r.items() if c.startswith("key.")}
        assert len(keys) == 34 and all(KEY.match(v) for v in keys.values())
        for col, key in keys.items():
            stage = col.removeprefix("key.").split("[")[0]
            assert (project / "artifacts" / "objects" / stage / key / "manifest.json").is_file()
    assert len({r["key.extract[reference]"] for r in rows}) == 1
    assert len({r["key.optimize[reference]"] for r in rows}) == 9
    # The best point is the lowest of the first metric beyond its noise, marked once, in the
    # CSV and the table; points that tie within the noise mark none.
    low = min(float(r[FIRST]) for r in rows)
    lowest = [r["point"] for r in rows if within_noise(float(r[FIRST]), low)]
    marked = [line.split()[0] for line in out.splitlines() if line.rstrip().endswith("*")]
    assert [r["point"] for r in rows if r["best"] == "true"] == marked
    if len(lowest) == 1:
        assert marked == lowest
        assert f"best (lowest trajectory.rmse_m): point {lowest[0]}:" in out
    else:
        assert marked == [] and f"best: none: points {', '.join(lowest)} give the same" in out
    # Progress: points done / total with an ETA once a point has been timed.
    assert "sweep: point 1/9 (optimize.loss=linear optimize.f_scale=0.05)\n" in err
    assert re.search(
        r"sweep: point 9/9 \(optimize\.loss=huber optimize\.f_scale=0\.2\) … "
        r"ETA [0-9.]+ s",
        err,
    )
    png = project / "sweeps" / NAME / "sweep.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert not [p for p in (project / "sweeps").rglob("*") if TEMP.match(p.name)]


def test_metrics_are_the_points_artifacts(swept: tuple[Path, str, str]) -> None:
    """Row 7's numbers, read back through an ordinary Runner given the same overrides."""
    project, _, _ = swept
    row = table(project)[6]
    sets = [f"optimize.loss={row['optimize.loss']}", f"optimize.f_scale={row['optimize.f_scale']}"]
    runner = Runner(load_pipeline(project / "pipeline.yaml", REGISTRY, sets))
    key = runner.key_of("eval", "reference")
    assert key == row["key.eval[reference]"]
    evaluation = runner.store.load("eval", key, "evaluation")
    assert float(row[FIRST]) == evaluation["trajectory"]["position_m"]["rmse"]
    key = runner.key_of("report", "query_2")
    summary = runner.store.load("report", key, "summary")
    assert float(row["D.mean_m[query_2]"]) == summary["distance_m"]["mean"]
    report = runner.store.load("optimize", row["key.optimize[reference]"], "report")
    assert float(row["map.rms_t_m[reference]"]) == report["rms_t_m"]
    assert (report["loss"], report["f_scale"]) == ("huber", 0.05)


def test_show_opens_a_points_artifacts(swept: tuple[Path, str, str], capsys: Capsys) -> None:
    project, _, _ = swept
    pipe = str(project / "pipeline.yaml")
    row = table(project)[3]
    capsys.readouterr()
    assert tagtrail.cli.main(["show", "optimize", "-p", pipe, "--point", "4"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"sweep {NAME}, point 4: optimize.loss=soft_l1 optimize.f_scale=0.05\n")
    assert f"artifact {row['key.optimize[reference]'][:12]}" in out
    assert (
        tagtrail.cli.main(
            [
                "show",
                "optimize",
                "-p",
                pipe,
                "--point",
                "4",
                "--sweep",
                NAME,
                "--dataset",
                "query_1",
                "--output",
                "report",
            ]
        )
        == 0
    )
    assert f"artifact {row['key.optimize[query_1]'][:12]}" in capsys.readouterr().out
    # the same -S as the point opens the same artifact
    assert (
        tagtrail.cli.main(
            [
                "show",
                "optimize",
                "-p",
                pipe,
                "-S",
                "optimize.loss=soft_l1",
                "-S",
                "optimize.f_scale=0.05",
            ]
        )
        == 0
    )
    assert f"artifact {row['key.optimize[reference]'][:12]}" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.skipif(
    importlib.util.find_spec("distributed") is None,
    reason="dask.distributed not installed (pip install -e '.[test]')",
)
def test_a_sweep_on_a_2_worker_dask_cluster_matches_the_local_one(
    swept: tuple[Path, str, str], data: Path, tmp_path: Path, capsys: Capsys
) -> None:
    """`sweep --executor dask`: every point on one LocalCluster, the same keys and metrics as
    the local sweep's points (nothing cached in the fresh project)."""
    project, _, _ = swept
    fresh = demo_project(tmp_path / "dask", data)
    rc, _, err = sweep(
        fresh,
        capsys,
        "-S",
        "optimize.loss=soft_l1",
        "-S",
        "optimize.f_scale=0.05,0.1",
        "--dataset",
        "reference",
        "--executor",
        "dask",
        "-j",
        "2",
    )
    assert rc == 0, err
    assert err.count("dask: a local cluster of 2 worker processes, dashboard") == 1
    (folder,) = (fresh / "sweeps").iterdir()
    rows = read_table(folder / "sweep.csv")
    local = {(r["optimize.loss"], r["optimize.f_scale"]): r for r in table(project)}
    assert [(r["optimize.loss"], r["optimize.f_scale"]) for r in rows] == [
        ("soft_l1", "0.05"),
        ("soft_l1", "0.1"),
    ]
    for r in rows:
        ref = local[(r["optimize.loss"], r["optimize.f_scale"])]
        shared = [c for c in r if c.startswith("key.") or c == FIRST]
        assert len(shared) > 5 and {c: r[c] for c in shared} == {c: ref[c] for c in shared}
        assert float(r["time_s.extract"]) > 0


def test_a_sweep_scheduler_needs_the_dask_executor(
    swept: tuple[Path, str, str], capsys: Capsys
) -> None:
    project, _, _ = swept
    rc, _, err = sweep(
        project,
        capsys,
        "-S",
        "optimize.f_scale=0.1",
        "--executor",
        "local",
        "--scheduler",
        "tcp://127.0.0.1:1",
    )
    assert rc == 2
    assert err.strip().splitlines() == ["error: --scheduler needs --executor dask"]


def test_rerun_of_a_finished_sweep_runs_nothing(
    swept: tuple[Path, str, str], capsys: Capsys, tmp_path: Path
) -> None:
    project, _, _ = swept
    before = table(project)
    rc, _, err = sweep(project, capsys, *GRID)
    assert rc == 0, err
    assert all(nodes == [] for nodes in ran(run_log(project)).values())
    after = table(project)
    assert strip(after) == strip(before) and all(r["ran"] == "0" for r in after)


@pytest.mark.slow
def test_a_killed_sweep_resumes_without_redoing_finished_points(data: Path, tmp_path: Path) -> None:
    project = demo_project(tmp_path / "killed", data)
    # Killed between points: after point 3's row was written.
    killed = cli(project, "sweep", *GRID, fault="kill@sweep:point-3")
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    rows = table(project)
    assert [r["point"] for r in rows] == ["1", "2", "3"]
    assert all(r["status"] == "ok" and r[FIRST] for r in rows)
    # Killed inside a stage: the resumed sweep finds points 1-3 cached (no optimize, no kill)
    # and dies in point 4's optimize, results computed but not stored.
    killed = cli(project, "sweep", *GRID, fault="kill@stage:optimize")
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert "sweep: point 4/9" in killed.stderr and "sweep: point 5/9" not in killed.stderr
    log = ran(run_log(project))
    assert list(log) == [1, 2, 3] and all(v == [] for v in log.values())
    again = table(project)
    assert strip(again) == strip(rows) and all(r["ran"] == "0" for r in again)
    # Resumed for good: the finished points rerun nothing, the rest run; nine rows.
    done = cli(project, "sweep", *GRID)
    assert done.returncode == 0, done.stderr
    log = ran(run_log(project))
    assert list(log) == list(range(1, 10))
    assert all(log[p] == [] for p in (1, 2, 3))
    assert all("optimize [reference]" in log[p] for p in range(4, 10))
    assert not any(n.startswith(("extract", "pnp", "edges")) for p in log for n in log[p])
    final = table(project)
    assert len(final) == 9 and all(r["status"] == "ok" and r[FIRST] for r in final)
    assert [r["key.optimize[reference]"] for r in final[:3]] == [
        r["key.optimize[reference]"] for r in rows
    ]
    assert len(list((project / "artifacts" / "objects" / "extract").iterdir())) == len(DATASETS)
    tmp = project / "artifacts" / "tmp"
    assert not (tmp.is_dir() and list(tmp.iterdir()))


def test_chosen_metrics_datasets_and_points_file(
    swept: tuple[Path, str, str], capsys: Capsys, tmp_path: Path
) -> None:
    project, _, _ = swept
    rc, out, err = sweep(
        project,
        capsys,
        "-S",
        "optimize.loss=linear,huber",
        "-S",
        "optimize.f_scale=0.1",
        "--metric",
        "D.mean_m",
        "--metric",
        "map.rms_px",
        "--metric",
        "gauge_free.tags.max_deg",
        "--dataset",
        "query_1",
        "--name",
        "picked",
    )
    assert rc == 0, err
    rows = table(project, "picked")
    cols = list(rows[0])
    assert [c for c in cols if "[" in c and not c.startswith("key.")] == [
        "D.mean_m[query_1]",
        "map.rms_px[query_1]",
        "gauge_free.tags.max_deg[query_1]",
    ]
    assert [r["map.rms_px[query_1]"] for r in rows] == ["", ""]  # 5 frames: no joint solve
    assert all(r["ran"] == "0" for r in rows)  # both points were in the 3×3 grid
    assert not any(c.endswith("[query_2]") for c in cols)  # query_2 neither ran nor was read
    d = [float(r["D.mean_m[query_1]"]) for r in rows]  # the loss barely moves a parked D:
    if within_noise(*d):  # the line names the best only beyond the metric's noise
        assert "best: none: points 1, 2 give the same D.mean_m" in out
    else:
        assert "best (lowest D.mean_m): point" in out
    # An explicit list (YAML) crossed with a one-valued -S; a mapping value is one value.
    points = tmp_path / "points.yaml"
    points.write_text(
        "- {optimize.f_scale: 0.1, pnp.tag_sizes: {1: 0.16}}\n- {optimize.f_scale: 0.2}\n"
    )
    rc, out, err = sweep(
        project,
        capsys,
        "--points",
        str(points),
        "-S",
        "optimize.loss=huber",
        "--metric",
        "tags.rmse_m",
    )
    assert rc == 0, err
    rows = table(project, "points")
    assert [(r["optimize.f_scale"], r["pnp.tag_sizes"], r["optimize.loss"]) for r in rows] == [
        ("0.1", "{1: 0.16}", "huber"),
        ("0.2", "", "huber"),
    ]
    definition = json.loads((project / "sweeps" / "points" / "sweep.json").read_text())
    assert definition["points"][0]["overrides"] == [
        "optimize.f_scale=0.1",
        "pnp.tag_sizes={1: 0.16}",
        "optimize.loss=huber",
    ]
    assert rows[1]["ran"] == "0"  # (huber, 0.2) was in the grid
    assert rows[0]["key.extract[reference]"] == table(project)[0]["key.extract[reference]"]


def test_a_point_that_fails_on_its_data_is_a_failed_row(
    swept: tuple[Path, str, str], capsys: Capsys
) -> None:
    project, _, _ = swept
    rc, out, err = sweep(
        project,
        capsys,
        "-S",
        "extract.min_decision_margin=100000,20",
        "--metric",
        "map.rms_t_m",
        "--dataset",
        "reference",
    )
    assert rc == 1, err
    failed, good = table(project, "extract.min_decision_margin")
    assert failed["status"].startswith("failed: extract [reference]: ")
    assert "no detection is left: min_decision_margin 100000 drops" in failed["status"]
    assert failed["map.rms_t_m[reference]"] == "" and failed["best"] == "false"
    assert good["status"] == "ok" and good["best"] == "true" and good["ran"] == "0"
    assert float(good["time_s.extract"]) > 0  # timed by the first sweep
    assert "1 point(s) failed: 1" in err
    assert re.search(r"^ +1 +100000 +- +failed$", out, re.M)


def test_value_lists_keep_yaml_flow_values_whole() -> None:
    assert split_values("linear, soft_l1,huber") == ["linear", "soft_l1", "huber"]
    assert split_values("{1: 0.1, 2: 0.2}") == ["{1: 0.1, 2: 0.2}"]
    assert split_values("{1: 0.1},{1: 0.2}") == ["{1: 0.1}", "{1: 0.2}"]
    assert split_values("[1, 2],[3,4]") == ["[1, 2]", "[3,4]"]
    assert split_values("'a,b',\"c,\\\"d\",it's") == ["'a,b'", '"c,\\"d"', "it's"]
    assert split_values("[a, 'b,]c'], d") == ["[a, 'b,]c']", "d"]
    points = make_points(["pnp.tag_sizes={1: 0.1, 2: 0.2},{1: 0.15}", "optimize.f_scale=1e-2"])
    assert [p.label for p in points] == [
        "pnp.tag_sizes={1: 0.1, 2: 0.2} optimize.f_scale=1e-2",
        "pnp.tag_sizes={1: 0.15} optimize.f_scale=1e-2",
    ]
    for value in ("huber", 0.05, {1: 0.1}, [1, 2], True, None, "1e-3", "a, b"):
        assert make_points([], [{"x.y": yaml_text(value)}])[0].values["x.y"] == yaml_text(value)
        from tagtrail.runner.spec import parse_override

        assert parse_override(f"x.y={yaml_text(value)}")[2] == value


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["-S", "optimize.f_scal=0.05,0.1"], "unknown key 'f_scal' — did you mean 'f_scale'?"),
        (["-S", "optimize.loss=linear,huber,bogus"], "sweep point 3/3 (optimize.loss=bogus): "),
        (
            ["-S", "optimize.loss=linear", "--metric", "trajectory.rmse"],
            "unknown metric 'trajectory.rmse' — did you mean 'trajectory.rmse_m'? (metrics: BLOCK.",
        ),
        (["-S", "optimize.loss="], "no values (expected optimize.loss=v1,v2,…)"),
        (["-S", "optimize.loss=linear,,huber"], "an empty value in the list"),
        (["-S", "optimize.loss=linear,linear"], "value 'linear' given twice"),
        (
            ["-S", "optimize.loss=linear", "-S", "optimize.loss=huber"],
            "-S optimize.loss given twice",
        ),
        ([], "nothing to sweep: give -S stage.param=v1,v2,… or --points FILE"),
        (["-S", "optimize.loss=linear", "--dataset", "query_9"], "--dataset query_9: unknown"),
        (
            ["-S", "optimize.loss=linear", "--metric", "D.mean_m", "--dataset", "reference"],
            "metric D.mean_m: no dataset of the sweep has it (report [reference] does not run: "
            "runs on query datasets only)",
        ),
        (["--points", "nope.csv"], "--points nope.csv: no such file"),
        (["-S", "optimize.loss=linear", "--name", "../x"], "sweep name '../x' is not allowed"),
        (["-S", "optimize=1,2"], "bad parameter 'optimize' (expected stage.param)"),
    ],
)
def test_bad_input_is_one_error_line(
    swept: tuple[Path, str, str], capsys: Capsys, argv: list[str], message: str
) -> None:
    project, _, _ = swept
    sweeps = sorted(p.name for p in (project / "sweeps").iterdir())
    capsys.readouterr()
    assert sweep_cmd.main(["-p", str(project / "pipeline.yaml"), *argv]) == 2
    assert message in one_error_line(capsys)
    assert sorted(p.name for p in (project / "sweeps").iterdir()) == sweeps  # nothing written


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--point", "10", "--sweep", NAME], f"sweep {NAME} has points 1..9, not 10"),
        (["--point", "1", "--sweep", "optimize.loss"], "no sweep 'optimize.loss' in"),
        (["--sweep", NAME], "give --point too"),
    ],
)
def test_show_point_errors(
    swept: tuple[Path, str, str], capsys: Capsys, argv: list[str], message: str
) -> None:
    project, _, _ = swept
    capsys.readouterr()
    assert tagtrail.cli.main(["show", "optimize", "-p", str(project / "pipeline.yaml"), *argv]) == 2
    assert message in one_error_line(capsys)


def test_points_csv_file_errors(tmp_path: Path) -> None:
    from tagtrail.errors import SpecError
    from tagtrail.runner.sweep import read_points

    f = tmp_path / "p.csv"
    f.write_text("optimize.loss,optimize.f_scale\nhuber,0.1\n\nlinear,\n")
    assert read_points(f) == [
        {"optimize.loss": "huber", "optimize.f_scale": "0.1"},
        {"optimize.loss": "linear"},
    ]
    f.write_text("optimize.loss\n")
    with pytest.raises(SpecError, match="no points"):
        read_points(f)
    f.write_text("optimize.loss\nhuber,0.1\n")
    with pytest.raises(SpecError, match="line 2: 2 cells for 1 columns"):
        read_points(f)
    y = tmp_path / "p.yaml"
    y.write_text("optimize.loss: huber\n")
    with pytest.raises(SpecError, match="expected a list of mappings"):
        read_points(y)
    y.write_text("- {optimize.loss: huber}\n- {optimize.loss: huber}\n")
    with pytest.raises(SpecError, match="points 1 and 2 are the same"):
        make_points([], read_points(y))

"""``tagtrail eval``: the paper's Tables 4.1/4.2 and A.1 from a real run of the pipeline, checked
against the simulator's ground truth and against the exported files (not the artifacts the command
reads), plus its one-line errors."""

from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

import tagtrail.cli
from tagtrail.commands import eval as eval_cmd
from tagtrail.geometry.se3 import T_from_xyz_quat, inv
from tagtrail.io.layouts import read_tag_map, read_trajectory
from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.schemas.artifacts import POSE_COLS
from tagtrail.stages import REGISTRY
from tests.cli_helpers import one_error_line

ERROR_METRICS = ["trajectory", "trajectory_raw", "tags", "gauge_free.trajectory", "gauge_free.tags"]
Capsys = pytest.CaptureFixture[str]
PIPELINE = """datasets:
  reference: {source: bags/reference}
  query: {source: bags/query_1}
stages:
  pnp: {tag_size: 0.16}
"""


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory, room_bags: Path) -> Path:
    """The `room` detection recordings, mapped and evaluated by ``tagtrail run eval``."""
    root = tmp_path_factory.mktemp("eval")
    shutil.copytree(room_bags, root / "bags")
    (root / "pipeline.yaml").write_text(PIPELINE)
    assert tagtrail.cli.main(["run", "eval", "-p", str(root / "pipeline.yaml")]) == 0
    return root


def run_eval(project: Path, capsys: Capsys, *argv: str) -> tuple[int, str, str]:
    """Exit code, stdout and stderr of ``tagtrail eval -p <project>/pipeline.yaml ARGV``."""
    capsys.readouterr()
    rc = eval_cmd.main(["-p", str(project / "pipeline.yaml"), *argv])
    out, err = capsys.readouterr()
    return rc, out, err


def error_line(err: str) -> str:
    """The single ``error: …`` line of a failed command's stderr."""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


def eval_json(project: Path, capsys: Capsys, *argv: str) -> dict[str, Any]:
    rc, out, err = run_eval(project, capsys, "--json", *argv)
    assert rc == 0, err
    doc: dict[str, Any] = json.loads(out)
    return doc


def positions(tags: pd.DataFrame) -> dict[int, np.ndarray]:
    return {
        int(t): p
        for t, p in zip(tags["tag_id"], tags[["x_m", "y_m", "z_m"]].to_numpy(), strict=True)
    }


def write_distances(path: Path, rows: list[tuple[str, str, float]]) -> Path:
    path.write_text(
        "source_tag,target_tag,measured_m\n" + "".join(f"{a},{b},{m!r}\n" for a, b, m in rows)
    )
    return path


def tape_from_ground_truth(project: Path, tmp_path: Path) -> tuple[Path, dict[int, np.ndarray]]:
    """A "tape-measured" CSV: the true distances of some tag pairs (both id spellings) and two
    pairs naming tags no map has."""
    gt = positions(read_tag_map(project / "bags" / "reference" / "ground_truth")[0])
    pairs = [("tag36h11:0", "2"), ("0", "tag36h11:3"), ("5", "9"), ("1", "14")]
    ids = [(int(a.split(":")[-1]), int(b.split(":")[-1])) for a, b in pairs]
    rows = [
        (a, b, float(np.linalg.norm(gt[i] - gt[j])))
        for (a, b), (i, j) in zip(pairs, ids, strict=True)
    ]
    rows += [("0", "999", 1.5), ("998", "999", 2.0)]
    return write_distances(tmp_path / "tape.csv", rows), gt


def test_errors_are_the_exported_evaluation_and_match_ground_truth(
    project: Path, capsys: Capsys
) -> None:
    doc = eval_json(project, capsys)
    assert doc["dataset"] == "reference" and doc["distances"] is None
    rows = {r["metric"]: r for r in doc["errors"]}
    assert list(rows) == ERROR_METRICS
    exported = json.loads((project / "outputs" / "reference" / "evaluation.json").read_text())
    assert doc["evaluation"] == exported
    for metric, r in rows.items():
        block = exported
        for part in metric.split("."):
            block = block[part]
        assert (r["n"], r["coverage"]) == (block["n"], block["coverage"])
        for s in ("mean", "min", "max"):
            assert r[f"{s}_m"] == block["position_m"][s] and r[f"{s}_deg"] == block["angle_deg"][s]
    gt_dir = project / "bags" / "reference" / "ground_truth"
    assert rows["trajectory"]["n"] == rows["trajectory_raw"]["n"] == len(read_trajectory(gt_dir))
    # The tag-pose row recomputed from the exported tag_map.csv and the simulator's tag map: the
    # ground truth re-expressed in the map's world (its anchor tag's frame), position errors.
    est, anchor = read_tag_map(project / "outputs" / "reference")
    gt = read_tag_map(gt_dir)[0].set_index("tag_id")
    assert anchor is not None and anchor == doc["evaluation"]["anchor_id"]
    a_T_gt = inv(
        T_from_xyz_quat(
            gt.loc[[anchor], POSE_COLS[:3]].to_numpy(), gt.loc[[anchor], POSE_COLS[3:]].to_numpy()
        )[0]
    )
    others = est[est["tag_id"] != anchor].set_index("tag_id")
    p_gt = (a_T_gt[:3, :3] @ gt.loc[others.index, POSE_COLS[:3]].to_numpy().T).T + a_T_gt[:3, 3]
    err = np.linalg.norm(others[POSE_COLS[:3]].to_numpy() - p_gt, axis=1)
    assert rows["tags"]["n"] == len(gt) - 1 == len(err)
    assert rows["tags"]["mean_m"] == pytest.approx(err.mean(), abs=1e-9)
    assert rows["tags"]["min_m"] == pytest.approx(err.min(), abs=1e-9)
    assert rows["tags"]["max_m"] == pytest.approx(err.max(), abs=1e-9)


def test_errors_text_table(project: Path, capsys: Capsys) -> None:
    rc, out, _ = run_eval(project, capsys)
    assert rc == 0
    rows = {r["metric"]: r for r in eval_json(project, capsys)["errors"]}
    lines = out.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("metric "))
    table = lines[head : head + 1 + len(ERROR_METRICS)]
    assert len({len(line) for line in table}) == 1, "columns are not aligned"
    for line, metric in zip(table[1:], ERROR_METRICS, strict=True):
        r = rows[metric]
        assert line.startswith(r["label"]) and ("gauge-free" in line) == metric.startswith("gauge")
        for s in ("mean", "min", "max"):
            assert f"{r[f'{s}_m']:.4f} m / {r[f'{s}_deg']:.2f}°" in line
        assert f" {r['n']} " in line and f"{100 * r['coverage']:.1f}%" in line
    assert "Tables 4.1/4.2" in out and "Table A.1" not in out


def test_distances_table_against_ground_truth(
    project: Path, capsys: Capsys, tmp_path: Path
) -> None:
    tape, gt = tape_from_ground_truth(project, tmp_path)
    doc = eval_json(project, capsys, "--distances", str(tape))
    assert [r["metric"] for r in doc["errors"]] == ERROR_METRICS  # both tables
    dist = doc["distances"]
    est = positions(read_tag_map(project / "outputs" / "reference" / "tag_map.csv")[0])
    ok = [p for p in dist["pairs"] if not p["missing"]]
    assert [(p["source_tag"], p["target_tag"]) for p in dist["pairs"]] == [
        (0, 2),
        (0, 3),
        (5, 9),
        (1, 14),
        (0, 999),
        (998, 999),
    ]
    errors = []
    for p in ok:
        a, b = p["source_tag"], p["target_tag"]
        true = float(np.linalg.norm(gt[a] - gt[b]))
        mine = float(np.linalg.norm(est[a] - est[b]))
        assert p["measured_m"] == true and p["status"] == "ok"
        assert p["estimated_m"] == pytest.approx(mine, rel=1e-12)
        assert p["abs_error_m"] == pytest.approx(abs(mine - true), abs=1e-12)
        assert p["rel_error_pct"] == pytest.approx(100 * abs(mine - true) / true, abs=1e-9)
        errors.append(abs(mine - true))
        assert abs(mine - true) < 0.10 * true  # the map is right to a few percent
    missing = dist["pairs"][4:]
    assert [p["missing"] for p in missing] == [[999], [998, 999]]
    assert all(p["estimated_m"] is p["abs_error_m"] is None for p in missing)
    assert (dist["n"], dist["n_missing"]) == (4, 2)
    assert dist["abs_error_m"] == pytest.approx(
        {"mean": np.mean(errors), "max": max(errors), "min": min(errors)}, abs=1e-12
    )

    rc, out, err = run_eval(project, capsys, "--distances", str(tape))
    assert rc == 0 and "Table A.1" in out and "Tables 4.1/4.2" in out
    text = out[out.index("Tag distances") :].splitlines()
    assert text[2].split()[:4] == ["source", "tag", "target", "tag"]
    row = next(line for line in text if line.startswith("5 "))
    p = ok[2]
    assert row.split() == [
        "5",
        "9",
        f"{p['estimated_m']:.3f}",
        f"{p['measured_m']:.3f}",
        f"{p['abs_error_m']:.3f}",
        f"{p['rel_error_pct']:.1f}",
    ]
    assert any(line.startswith("998 ") and "missing: tag 998 and tag 999" in line for line in text)
    mean = next(line for line in text if line.startswith("Mean "))
    assert mean.split()[4] == f"{dist['abs_error_m']['mean']:.3f}"


def test_csv_export_has_both_tables(project: Path, capsys: Capsys, tmp_path: Path) -> None:
    tape, _ = tape_from_ground_truth(project, tmp_path)
    doc = eval_json(project, capsys, "--distances", str(tape))
    csv_file = tmp_path / "e.csv"
    rc, out, _ = run_eval(project, capsys, "--distances", str(tape), "--csv", str(csv_file))
    assert rc == 0 and f"wrote {csv_file}" in out and "Table A.1" in out
    df = pd.read_csv(csv_file)
    assert list(df.columns) == list(eval_cmd.CSV_COLUMNS)
    errs, dist = df[df["table"] == "errors"], df[df["table"] == "distances"]
    assert len(errs) + len(dist) == len(df)
    assert list(errs["metric"]) == ERROR_METRICS
    for (_, r), j in zip(errs.iterrows(), doc["errors"], strict=True):
        assert r["n"] == j["n"] and r["mean_m"] == pytest.approx(j["mean_m"], rel=1e-15)
        assert r["max_deg"] == pytest.approx(j["max_deg"], rel=1e-15)
    pairs = dist[dist["metric"] == "pair"]
    assert len(pairs) == len(doc["distances"]["pairs"])
    for (_, r), j in zip(pairs.iterrows(), doc["distances"]["pairs"], strict=True):
        assert (r["source_tag"], r["target_tag"], r["status"]) == (
            j["source_tag"],
            j["target_tag"],
            j["status"],
        )
        assert (
            pd.isna(r["estimated_m"])
            if j["estimated_m"] is None
            else r["estimated_m"] == pytest.approx(j["estimated_m"], rel=1e-15)
        )
    stats = dist[dist["metric"] != "pair"].set_index("metric")["abs_error_m"]
    assert stats.to_dict() == pytest.approx(doc["distances"]["abs_error_m"], rel=1e-15)


def test_another_dataset(project: Path, capsys: Capsys) -> None:
    doc = eval_json(project, capsys, "--dataset", "query")
    exported = json.loads((project / "outputs" / "query" / "evaluation.json").read_text())
    assert doc["dataset"] == "query" and doc["evaluation"] == exported
    rc, out, err = run_eval(project, capsys, "--dataset", "query")
    assert rc == 0 and "[query]" in out


BAD_CSV = [
    ("source_tag,target_tag,dist\n0,2,1.0\n", "missing column measured_m"),
    (
        "source_tag,target_tag,measured_m\n0,2,1.0\n0,3,abc\n",
        "data row 2 (line 3), column measured_m: 'abc' is not a number",
    ),
    (
        "source_tag,target_tag,measured_m\n0,tag36h11:x,1.0\n",
        "data row 1 (line 2), column target_tag: 'tag36h11:x' is not a tag id",
    ),
    ("source_tag,target_tag,measured_m\n0,2.5,1.0\n", "data row 1 (line 2), column target_tag"),
    (
        "source_tag,target_tag,measured_m\n0,2,1\n\n,2,1.0\n",
        "data row 2 (line 4), column source_tag: empty cell is not a tag id",
    ),
    ("source_tag,target_tag,measured_m\n0,2,-0.5\n", "column measured_m: '-0.5' is not a positive"),
    ("source_tag,target_tag,measured_m\n0,2,nan\n", "column measured_m: 'nan' is not a positive"),
    ("source_tag,target_tag,measured_m\n0,2\n", "data row 1 (line 2), column measured_m: missing"),
    ("source_tag,target_tag,measured_m\n3,3,1.0\n", "column target_tag: tag 3 is also the source"),
    ("source_tag,target_tag,measured_m\n", "no tag pairs"),
    ("", "empty file"),
]


@pytest.mark.parametrize("text, message", BAD_CSV)
def test_bad_distances_csv_is_one_line(
    project: Path, capsys: Capsys, tmp_path: Path, text: str, message: str
) -> None:
    f = tmp_path / "tape.csv"
    f.write_text(text)
    rc, out, err = run_eval(project, capsys, "--distances", str(f))
    line = error_line(err)
    assert rc == 2 and out == ""
    assert line.startswith(f"error: {f}: ") and message in line, line


def test_distances_csv_with_a_bom_extra_columns_and_blank_lines(tmp_path: Path) -> None:
    f = tmp_path / "tape.csv"
    f.write_text(
        '\ufeffnote, measured_m ,source_tag,target_tag\n"wall, left",1.38,16,tag36h11:2\n'
        "\n,0.48, 16 ,14\n",
        encoding="utf-8",
    )
    pairs = eval_cmd.read_distances(f)
    assert [(p.source_tag, p.target_tag, p.measured_m) for p in pairs] == [
        (16, 2, 1.38),
        (16, 14, 0.48),
    ]


def test_missing_distances_file(project: Path, capsys: Capsys, tmp_path: Path) -> None:
    rc, _, err = run_eval(project, capsys, "--distances", str(tmp_path / "nope.csv"))
    assert rc == 2 and f"{tmp_path / 'nope.csv'}: no such file" in error_line(err)


@pytest.fixture(scope="module")
def unrun(project: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A pipeline over the same recording (and a copy of it without ground truth), never run."""
    root = tmp_path_factory.mktemp("unrun")
    shutil.copytree(
        project / "bags" / "reference",
        root / "plain",
        ignore=shutil.ignore_patterns("ground_truth"),
    )
    (root / "pipeline.yaml").write_text(
        f"datasets:\n  reference: {{source: {project / 'bags' / 'reference'}}}\n"
        "  plain: {source: plain}\nstages:\n  pnp: {tag_size: 0.16}\n"
    )
    return root


def test_not_run_yet_is_one_line(unrun: Path, capsys: Capsys, tmp_path: Path) -> None:
    pipeline = unrun / "pipeline.yaml"
    rc, out, err = run_eval(unrun, capsys)
    assert rc == 2 and out == ""
    assert error_line(err) == (
        f"error: eval [reference] is not up to date: run `tagtrail run eval -p {pipeline}` first"
    )
    tape = write_distances(tmp_path / "tape.csv", [("0", "2", 2.0)])
    rc, _, err = run_eval(unrun, capsys, "--dataset", "plain", "--distances", str(tape))
    assert rc == 2
    assert error_line(err) == (
        f"error: optimize [plain] is not up to date: run "
        f"`tagtrail run optimize -p {pipeline}` first"
    )
    assert not (unrun / "artifacts" / "objects").exists()  # eval computes nothing


def test_no_ground_truth_needs_distances(unrun: Path, capsys: Capsys) -> None:
    rc, _, err = run_eval(unrun, capsys, "--dataset", "plain")
    assert rc == 2 and "dataset plain has no ground truth" in error_line(err)
    rc, _, err = run_eval(unrun, capsys, "--dataset", "plian")
    assert rc == 2 and "did you mean 'plain'" in error_line(err)


def test_overrides_select_the_run(project: Path, capsys: Capsys, tmp_path: Path) -> None:
    """-S names the run: artifacts made without the override are not that run's."""
    rc, _, err = run_eval(project, capsys, "-S", "optimize.f_scale=0.05")
    line = error_line(err)
    assert rc == 2 and "eval [reference] is not up to date" in line
    assert "-S optimize.f_scale=0.05` first" in line
    rc, _, err = run_eval(project, capsys, "-S", "optimize.f_scal=0.05")
    assert rc == 2 and "did you mean 'f_scale'" in error_line(err)


def test_through_the_tagtrail_command(
    project: Path, capsys: Capsys, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The registration line for cli.OPTIONAL (added here if cli.py does not have it yet)."""
    if not any(name == "eval" for name, *_ in tagtrail.cli.OPTIONAL):
        monkeypatch.setattr(
            tagtrail.cli,
            "OPTIONAL",
            (
                *tagtrail.cli.OPTIONAL,
                ("eval", "tagtrail.commands.eval", "the paper's evaluation tables from a run"),
            ),
        )
    capsys.readouterr()
    assert tagtrail.cli.main(["eval", "-p", str(project / "pipeline.yaml"), "--json"]) == 0
    assert [r["metric"] for r in json.loads(capsys.readouterr().out)["errors"]] == ERROR_METRICS
    monkeypatch.chdir(project)
    tape = write_distances(tmp_path / "t.csv", [("0", "1", 1.0), ("0", "x", 1.0)])
    assert tagtrail.cli.main(["eval", "--distances", str(tape)]) == 2
    assert "data row 2 (line 3), column target_tag" in one_error_line(capsys)


# --- real photos ------------------------------------------------------------------------------


def dropped_tags(pipeline: Path, overrides: list[str]) -> list[int]:
    """The tags the last run's tag graph left out (not connected to its anchor)."""
    runner = Runner(load_pipeline(pipeline, REGISTRY, overrides))
    key = runner.key_of("edges", "reference")
    assert key is not None
    return [d.tag_id for d in runner.store.load("edges", key, "graph").dropped]


def test_photonvision_table_a1_from_the_official_layout(
    realdata: Path, tmp_path: Path, capsys: Capsys
) -> None:
    """Table A.1 on real photos of the FRC 2024 field with the official layout as the "tape":
    each connected group of tags is mapped in turn (``-S edges.anchor_id``, which ``eval`` takes
    too) and every pair of the layout's 16 tags is reported, estimated or missing."""
    root = realdata / "photonvision_frc2024_field"
    layout = {
        t["ID"]: np.array([t["pose"]["translation"][k] for k in "xyz"])
        for t in json.loads((root / "2024-crescendo.json").read_text())["tags"]
    }
    tape = write_distances(
        tmp_path / "layout.csv",
        [
            (f"tag36h11:{a}", str(b), float(np.linalg.norm(layout[a] - layout[b])))
            for a, b in itertools.combinations(sorted(layout), 2)
        ],
    )
    pipeline = tmp_path / "pipeline.yaml"
    pipeline.write_text(
        f"datasets:\n  reference: {{source: {root / 'images'}}}\n"
        "stages:\n  pnp: {tag_size: 0.1651}\n"
    )
    rel: dict[tuple[int, int], float] = {}
    pending: list[int | None] = [None]
    seen: set[int] = set()
    shown: list[str] = []
    while pending:
        anchor = pending.pop(0)
        overrides = [] if anchor is None else [f"edges.anchor_id={anchor}"]
        sets = [a for o in overrides for a in ("-S", o)]
        assert tagtrail.cli.main(["run", "optimize", "-p", str(pipeline), *sets]) == 0
        doc = eval_json(tmp_path, capsys, *sets, "--distances", str(tape))
        assert doc["errors"] is None  # no ground truth: Table A.1 only
        mapped = positions(read_tag_map(tmp_path / "outputs" / "reference")[0])
        seen |= set(mapped)
        for p in doc["distances"]["pairs"]:
            a, b = p["source_tag"], p["target_tag"]
            assert p["missing"] == [t for t in (a, b) if t not in mapped]
            if not p["missing"]:
                assert p["estimated_m"] == pytest.approx(np.linalg.norm(mapped[a] - mapped[b]))
                rel[a, b] = p["rel_error_pct"]
        assert doc["distances"]["n"] == len(list(itertools.combinations(mapped, 2)))
        if anchor is None:
            _, out, _ = run_eval(tmp_path, capsys, "--distances", str(tape))
            shown = [ln for ln in out.splitlines() if "missing" not in ln]  # printed at the end
            pending = list(dropped_tags(pipeline, overrides))
        pending = [t for t in pending if t not in seen]
    print("\n" + "\n".join(shown))
    print(
        f"pairs mapped together: {sorted(rel)}; relative error median "
        f"{np.median(list(rel.values())):.2f} %, max {max(rel.values()):.2f} %"
    )
    assert {(3, 4), (7, 8), (9, 10)} <= set(rel)
    # as tests/test_realdata_maps.py: single photos 1-6 m from the tags, a calibration of another
    # unit of the same camera model -> distances within a few percent of the official layout
    assert np.median(list(rel.values())) < 3 and max(rel.values()) < 5

"""End-to-end accuracy against the simulator's ground truth (issues 4 and 5).

Each test simulates into ``tmp_path`` (the simulator's defaults, seed 0), runs the whole
pipeline through the runner and compares with ground-truth files the pipeline never read:
``eval`` (trajectory / tag-map errors) and, for the room's parked queries, D and phi computed by
the report function from the ground-truth reference trajectory and test pose
(:func:`tagtrail.commands.demo.truth_d_phi`).

Issue 4 targets (circle): mean error <= 10 mm for both the trajectory and the tags, trajectory
p95 <= 30 mm — from images, from a ``--detections`` bag (MCAP) and from an sqlite3 bag.
Issue 5 targets (room demo, parked queries): |D - D_true| <= 5 mm, |phi - phi_true| <= 0.5 deg.

Two error definitions (``eval``): *anchored* -- world = the anchor tag's frame, as SPEC defines it
-- and *gauge-free* -- after the one rigid motion that best fits the estimated tag positions to
ground truth. They differ by the anchor tag's own pose error: the yaw/pitch of a 16 cm tag seen
near frontally is the least observable quantity of the problem (its corners pin it to ~7 deg per
frame at 1.5 m with 0.3 px noise), and world inherits it, levered over the 4.6 m ring. The issue
targets are asserted on the gauge-free errors; the anchored ones are asserted at what is
achieved, with the reason. Measured when this file was written (default seed 0, full circle):

- circle, detections (unbiased 0.3 px corner noise): gauge-free trajectory 1.6 / tags 1.0 mm;
  anchored 2.3 / 2.2 mm -- but 4.7 / 6.1 and 23.1 / 27.8 mm with seeds 1 and 2 (before tags cut
  by the image border were dropped): the anchor's yaw is off by 0.04-0.54 deg, pure noise (the
  pose graph alone: 30.9 / 33.4 mm).
- circle, images: the detector's own corners are ~0.06-0.1 px off (a bias of pupil-apriltags'
  edge refinement, measured on an exact render, tests/io/test_corners.py), which pitched the
  anchor by 0.25 deg and left 9.1 / 11.2 mm anchored. ``extract`` now re-fits the corners to the
  border's edges (``io.corners``, ~0.015 px) and drops tags cut by the image border: anchored
  4.1 (p95 6.1) / 4.8 mm (the anchor off by 0.09 deg), gauge-free 0.3 / 0.2 mm.
- room demo (jpeg images, full loop): map 5.7 / 5.9 mm anchored (2.1 / 1.0 gauge-free); parked
  queries' D errors 0.6 / 0.5 / 2.7 mm, phi errors 0.29 / 0.18 / 0.12 deg (before the corner
  re-fit, seeds 1-4: D <= 3.0 mm, phi <= 0.45 deg). phi compares the query's heading with the
  heading of ONE 1-cm segment of the smoothed reference path, so it needs the smoother's weights
  of ``smooth`` (0.81 -> 0.60 deg RMS segment heading error) and a reference path without the
  unphysical heading kinks the simulator's corners had (``sim.scene.ease_curvature``: query_3
  sat on one, 2.2-2.3 deg).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
import pytest

from tagtrail.commands import demo
from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.sim import simulate
from tagtrail.stages import REGISTRY

pytestmark = pytest.mark.slow  # accuracy against ground truth on rendered scenes (make test-all)


def run(folder: Path, pipeline: str) -> Runner:
    (folder / "pipeline.yaml").write_text(pipeline)
    runner = Runner(load_pipeline(folder / "pipeline.yaml", REGISTRY))
    runner.run()
    return runner


def artifact(runner: Runner, stage: str, output: str, dataset: str) -> Any:
    key = next(s.key for s in runner.plan() if s.stage == stage and s.dataset == dataset)
    return runner.store.load(stage, key, output)


def circle(folder: Path, **sim: Any) -> dict[str, Any]:
    simulate("circle", folder / "data", **sim)  # the simulator's defaults: 942 frames, seed 0
    runner = run(
        folder,
        "reference: circle\ndatasets:\n  circle:\n    source: data/circle\n"
        "stages:\n  pnp:\n    tag_size: 0.16\n"
        "  optimize:\n    method: joint\n",
    )
    return artifact(runner, "eval", "evaluation", "circle")


def mm(ev: dict[str, Any], block: str, stat: str = "mean") -> float:
    return 1000.0 * ev[block]["position_m"][stat]


def check_issue_4(ev: dict[str, Any]) -> None:
    """The issue's targets on the gauge-free errors (module docstring)."""
    free = ev["gauge_free"]
    print(
        f"\ncircle: trajectory {mm(ev, 'trajectory'):.1f} mm (p95 "
        f"{mm(ev, 'trajectory', 'p95'):.1f}), tags {mm(ev, 'tags'):.1f} mm; gauge-free "
        f"{mm(free, 'trajectory'):.1f} (p95 {mm(free, 'trajectory', 'p95'):.1f}) / "
        f"{mm(free, 'tags'):.1f} mm; anchor off by {free['rotation_deg']:.2f} deg"
    )
    assert ev["trajectory"]["coverage"] > 0.95 and ev["tags"]["n"] == 23
    assert mm(free, "trajectory") <= 10.0 and mm(free, "trajectory", "p95") <= 30.0
    assert mm(free, "tags") <= 10.0


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_circle_from_detections(tmp_path: Path, storage: str) -> None:
    ev = circle(tmp_path, detections=True, storage=storage)
    check_issue_4(ev)
    free = ev["gauge_free"]
    assert mm(free, "trajectory") <= 3.0 and mm(free, "tags") <= 2.0  # measured 1.6 / 1.0
    # Anchored: 2.3 / 2.2 mm (p95 4.1) at this seed, but the anchor's yaw is noise: 23 / 28 mm
    # (p95 35) at seed 2. The bound holds for the anchor errors seen over seeds 0-5.
    assert mm(ev, "trajectory") <= 30.0 and mm(ev, "tags") <= 35.0


def test_circle_from_images(tmp_path: Path) -> None:
    ev = circle(tmp_path)
    check_issue_4(ev)
    free = ev["gauge_free"]
    assert mm(free, "trajectory") <= 2.0 and mm(free, "tags") <= 1.5  # measured 0.3 / 0.2
    # Anchored, the issue's targets (measured 4.1, p95 6.1 / 4.8 mm with the corner re-fit)
    assert mm(ev, "trajectory") <= 10.0 and mm(ev, "trajectory", "p95") <= 30.0
    assert mm(ev, "tags") <= 10.0


def test_room_demo_parked_queries(tmp_path: Path) -> None:
    pipe = demo.prepare(tmp_path)  # exactly `tagtrail demo`: 914 + 3 x 30 frames, seed 0
    runner = Runner(load_pipeline(pipe, REGISTRY))
    runner.run()
    ev = artifact(runner, "eval", "evaluation", "reference")
    free = ev["gauge_free"]
    print(
        f"\nroom map: trajectory {mm(ev, 'trajectory'):.1f} mm, tags {mm(ev, 'tags'):.1f} mm; "
        f"gauge-free {mm(free, 'trajectory'):.1f} / {mm(free, 'tags'):.1f} mm"
    )
    assert mm(ev, "trajectory") <= 10.0 and mm(ev, "tags") <= 10.0  # measured 5.7 / 5.9
    assert mm(free, "trajectory") <= 4.0 and mm(free, "tags") <= 3.0  # measured 2.1 / 1.0
    gt_ref = tmp_path / "data" / "reference" / "ground_truth"
    errors = {}
    for q in ("query_1", "query_2", "query_3"):
        summary = artifact(runner, "report", "summary", q)
        reloc = artifact(runner, "report", "relocalization", q)
        assert summary["mode"] == "point" and len(reloc) == 1
        truth = demo.truth_d_phi(gt_ref, tmp_path / "data" / q / "ground_truth", "auto")
        d_err = 1000.0 * abs(summary["distance_m"]["median"] - truth["distance_m"])
        phi_err = abs(float(reloc["heading_error_deg"].iloc[0]) - truth["heading_error_deg"])
        errors[q] = (round(d_err, 2), round(phi_err, 3))
    print("\nroom parked queries: |D error| mm, |phi error| deg:", errors)
    for q, (d_err, phi_err) in errors.items():
        assert d_err <= 5.0 and phi_err <= 0.5, (q, errors)  # issue 5


def test_sparse_hall_from_detections_with_the_defaults(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 12's sparse scene (``tagtrail simulate hall``: 28 tags flat on the walls, seen at
    50-65 deg, 1-3 in view) from a detections bag, with the pipeline ``tagtrail init`` writes:
    every tag in one map, every frame that sees a tag posed, and the issue's sparse-scene
    bounds (trajectory mean <= 2.5 cm, max <= 10 cm, tags <= 2 cm; measured 1.3 / 3.1 /
    1.2 cm). The paper's pairwise map, trajectory and smoother on the same data are worse."""
    from tagtrail.cli import main

    rec = simulate("hall", tmp_path / "data", detections=True, storage="sqlite3")["hall"]
    monkeypatch.chdir(tmp_path)
    assert main(["init", "--reference", str(rec), "--tag-size", "0.16"]) == 0
    assert main(["run"]) == 0
    runner = Runner(load_pipeline(tmp_path / "pipeline.yaml", REGISTRY))
    assert all(s.status == "cached" for s in runner.plan())
    ev = artifact(runner, "eval", "evaluation", "reference")
    tags = artifact(runner, "optimize", "tag_map", "reference")
    report = artifact(runner, "optimize", "report", "reference")
    seen = artifact(runner, "pnp", "observations", "reference")["frame_idx"].nunique()
    traj = artifact(runner, "smooth", "trajectory", "reference")
    print(
        f"\nhall: trajectory {mm(ev, 'trajectory'):.1f} mm (max "
        f"{mm(ev, 'trajectory', 'max'):.1f}), tags {mm(ev, 'tags'):.1f} mm, {len(traj)} of "
        f"{seen} frames posed"
    )
    assert report["method"] == "joint" and len(tags) == 28
    assert len(traj) >= 0.95 * seen and traj["motion_prior"].all()
    assert mm(ev, "trajectory") <= 25.0 and mm(ev, "trajectory", "max") <= 100.0
    assert mm(ev, "tags") <= 20.0
    assert (tags["std_pos_m"] > 0).sum() == len(tags) - 1  # all but the anchor
    out = tmp_path / "outputs" / "reference"
    std = pd.read_csv(out / "trajectory_std.csv")
    assert len(std) == len(traj) and (std["std_pos_m"] > 0).all()
    diag = dict(line.split(",", 1) for line in (out / "diagnostics.csv").read_text().split()[1:])
    assert diag["map_method"] == "joint" and int(diag["joint_frames"]) == len(traj)
    assert "poorly_constrained_tags" in diag and (out / "map.png").stat().st_size > 0

    paper = Runner(
        load_pipeline(
            tmp_path / "pipeline.yaml",
            REGISTRY,
            ["optimize.method=pairwise", "trajectory.method=lsq"],
        )
    )
    paper.run()
    ev_paper = artifact(paper, "eval", "evaluation", "reference")
    print(
        f"hall, pairwise: trajectory {mm(ev_paper, 'trajectory'):.1f} mm, tags "
        f"{mm(ev_paper, 'tags'):.1f} mm"
    )
    assert mm(ev_paper, "trajectory") > mm(ev, "trajectory")


def test_sparse_corridor_images_mirrored_pairs_decided_by_continuity(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The corridor (``tagtrail simulate corridor``: 9 tags on alternate walls, a chain: each
    pair the only link) rendered with twice the default image noise and blur, on the detector's
    own corners (``extract.refit_corners: false``; the re-fit's corners are good enough there
    that nothing needs flipping: 2.5 cm): three pairs are seen only while the view hardly
    changes, and for them the mirrored IPPE solution of one tag is the lower-reprojection one in
    most of the frames -- a consistent wrong edge that bends the map by metres (tags) whatever
    the pose graph's loss. ``edges`` keeps the runner-up combination of such pairs and
    ``optimize`` takes it where the frames' continuity agrees better. Measured: trajectory
    3.8 cm mean / 6.6 cm max, tags 2.4 cm, gauge-free: the anchor sits at one end of the 8 m
    chain, where its own yaw error levers."""
    from dataclasses import replace

    from tagtrail.cli import main
    from tagtrail.sim.render import Realism

    rec = simulate(
        "corridor", tmp_path / "data", realism=replace(Realism(), noise_sigma=4.0, blur_sigma=1.0)
    )["corridor"]
    monkeypatch.chdir(tmp_path)
    assert main(["init", "--reference", str(rec), "--tag-size", "0.16"]) == 0
    raw = "extract.refit_corners=false"
    assert main(["run", "-S", raw]) == 0
    runner = Runner(load_pipeline(tmp_path / "pipeline.yaml", REGISTRY, [raw]))
    ev = artifact(runner, "eval", "evaluation", "reference")

    def free(e: Any) -> dict[str, Any]:
        return e["gauge_free"]

    graph = artifact(runner, "edges", "graph", "reference")
    report = artifact(runner, "optimize", "report", "reference")
    print(
        f"\ncorridor, images x2 noise: trajectory {mm(free(ev), 'trajectory'):.1f} mm (max "
        f"{mm(free(ev), 'trajectory', 'max'):.1f}), tags {mm(free(ev), 'tags'):.1f} mm; "
        f"rival pairs {[(p.tag_i, p.tag_j) for p in graph.rival_pairs]}, flipped "
        f"{report['bundle']['rival_pairs_flipped']}"
    )
    assert graph.n_components == 1 and len(graph.tags) == 9
    assert report["bundle"]["rival_pairs_flipped"]
    assert mm(free(ev), "trajectory", "max") <= 100.0 and mm(free(ev), "tags") <= 40.0

    blind = Runner(
        load_pipeline(
            tmp_path / "pipeline.yaml", REGISTRY, [raw, "optimize.branch_check=no_rivals"]
        )
    )
    blind.run()
    ev_blind = artifact(blind, "eval", "evaluation", "reference")
    assert mm(free(ev_blind), "tags") > 10 * mm(free(ev), "tags")  # the bent map


def test_ground_plane_and_wheels_keep_a_corridor_of_tags_level_and_straight(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The corridor from detections at twice the default corner noise (0.6 px), the defaults
    ``tagtrail init`` writes: the robot's camera rides a plane, ``auto`` sees that and applies
    the ground-plane prior, and the 9-tag chain no longer bends out of the floor; the robot
    drives on wheels, ``auto`` finds the drive prior costs the corners nothing and applies it,
    and the camera no longer wanders sideways where the tags in view change. Measured
    (gauge-free): trajectory 1.20 cm mean / 2.43 cm max, tags 0.76 cm; without the drive prior
    (``drive: free``) 2.81 / 9.85 / 1.80 cm; without either (``ground: none``) 5.0 / 11.2 / 3.0
    cm."""
    from tagtrail.cli import main

    # without /odom: the wheel-odometry prior would do the drive prior's work (issue 27)
    rec = simulate("corridor", tmp_path / "data", detections=True, corner_noise_px=0.6, odom=False)[
        "corridor"
    ]
    monkeypatch.chdir(tmp_path)
    assert main(["init", "--reference", str(rec), "--tag-size", "0.16"]) == 0
    assert main(["run"]) == 0
    runner = Runner(load_pipeline(tmp_path / "pipeline.yaml", REGISTRY))
    ground = artifact(runner, "optimize", "report", "reference")["bundle"]["ground"]
    assert ground["mode"] == "auto" and ground["applied"] and ground["planarity"] < 2.0
    assert ground["drive"].mode == "auto" and ground["drive"].applied  # a DriveReport (pydantic)
    ev = artifact(runner, "eval", "evaluation", "reference")["gauge_free"]

    def other(*overrides: str) -> Any:
        r = Runner(load_pipeline(tmp_path / "pipeline.yaml", REGISTRY, list(overrides)))
        r.run()
        return artifact(r, "eval", "evaluation", "reference")["gauge_free"]

    ev_free = other("optimize.joint.drive=free")  # the trajectory takes the map's settings
    ev_none = other("optimize.joint.ground=none")
    print(
        f"\ncorridor, 0.6 px: trajectory {mm(ev, 'trajectory'):.1f} mm (max "
        f"{mm(ev, 'trajectory', 'max'):.1f}), tags {mm(ev, 'tags'):.1f} mm; drive free "
        f"{mm(ev_free, 'trajectory'):.1f} / {mm(ev_free, 'tags'):.1f} mm; ground none "
        f"{mm(ev_none, 'trajectory'):.1f} / {mm(ev_none, 'tags'):.1f} mm"
    )
    assert mm(ev_free, "trajectory") <= 0.7 * mm(ev_none, "trajectory")
    assert mm(ev_free, "tags") <= 0.7 * mm(ev_none, "tags")
    assert mm(ev, "trajectory") <= 0.6 * mm(ev_free, "trajectory")
    assert mm(ev, "tags") <= 0.6 * mm(ev_free, "tags")
    assert mm(ev, "trajectory") <= 25.0 and mm(ev, "trajectory", "max") <= 100.0
    assert mm(ev, "tags") <= 20.0

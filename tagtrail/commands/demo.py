"""``tagtrail demo``: simulate the `room` recordings, run every stage, print one summary.

The summary compares what the pipeline estimated with what the simulator knows: map and
trajectory error vs ground truth, and for each parked query D and phi beside their ground-truth
values (computed by the same report function from the ground-truth reference trajectory and the
ground-truth test pose, neither of which the pipeline saw).
"""

from __future__ import annotations

import argparse
import json
from importlib import resources
from pathlib import Path
from typing import Any

from tagtrail.io.layouts import atomic_write_text, read_trajectory

RECORDINGS = ("reference", "query_1", "query_2", "query_3")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "examples:\n  tagtrail demo\n  tagtrail demo --dir /tmp/demo -j 2"
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--dir", type=Path, default=Path("demo"), help="demo folder (./demo)")
    parser.add_argument("-j", "--jobs", type=int, default=2, help="stages run in parallel (2)")
    parser.add_argument(
        "--frames",
        type=int,
        default=None,
        help="frames of the reference recording (default: the full loop)",
    )
    parser.add_argument(
        "--resimulate", action="store_true", help="render the recordings again even if they exist"
    )


def template() -> str:
    return resources.files("tagtrail").joinpath("templates/demo_pipeline.yaml").read_text()


def prepare(folder: Path, frames: int | None = None, resimulate: bool = False) -> Path:
    """Simulate the demo data into ``folder/data`` (once) and write ``folder/pipeline.yaml``."""
    from tagtrail.sim import simulate

    data = folder / "data"
    if resimulate or not all((data / r).is_dir() for r in RECORDINGS):
        print(f"simulating the `room` recordings into {data} …")
        simulate("room", data, compressed=True, frames=frames, progress=True, force=True)
    pipe = folder / "pipeline.yaml"
    atomic_write_text(pipe, template())
    return pipe


def truth_d_phi(gt_reference: Path, gt_query: Path, plane: str) -> dict[str, Any]:
    """D and phi of a parked ground-truth test pose against the ground-truth reference path."""
    from tagtrail.stages import align, report

    ref = read_trajectory(gt_reference / "trajectory.csv")
    test_pose = read_trajectory(gt_query / "test_poses.csv")
    out = report.run(
        trajectory=test_pose,
        ref_trajectory=ref,
        alignment=align.alignment_block("none", None, 0, 2),
        params=report.Params(mode="point", plane=plane),  # type: ignore[arg-type]
    )
    row = out["relocalization"].iloc[0]
    return {
        "distance_m": float(row["distance_m"]),
        "heading_error_deg": float(row["heading_error_deg"]),
    }


def main(args: argparse.Namespace) -> int:
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.export import export_outputs
    from tagtrail.runner.paths import check_project
    from tagtrail.runner.spec import load_pipeline
    from tagtrail.stages import REGISTRY

    folder = Path(args.dir)
    pipe_file = prepare(folder, args.frames, args.resimulate)
    runner = Runner(load_pipeline(pipe_file, REGISTRY), jobs=args.jobs, echo=print)
    check_project(runner.pipe)  # every path the run and its export write, before any work
    runner.run()
    written = export_outputs(runner)
    print()
    print(summarize(runner, written))
    return 0


def _fmt_err(block: dict[str, Any], unit: str) -> str:
    return (
        f"mean {block['mean']:.4f} {unit}, rmse {block['rmse']:.4f}, "
        f"p95 {block['p95']:.4f}, max {block['max']:.4f}"
    )


def summarize(runner: Any, written: dict[str, Path]) -> str:
    """The demo's closing report: accuracy vs ground truth and where the files are."""
    pipe = runner.pipe
    keys = {(s.stage, s.dataset): s.key for s in runner.plan() if s.status == "cached"}

    def art(stage: str, output: str, dataset: str) -> Any:
        key = keys.get((stage, dataset))
        return None if key is None else runner.store.load(stage, key, output)

    lines = ["== tagtrail demo summary"]
    ev = art("eval", "evaluation", pipe.reference)
    if ev:
        lines.append(
            f"reference map ({ev.get('tags', {}).get('n', '?')} tags) and trajectory "
            "vs ground truth:"
        )
        for what in ("trajectory", "tags"):
            block = ev.get(what, {})
            if "position_m" in block:
                lines.append(f"  {what:<10} position {_fmt_err(block['position_m'], 'm')}")
                lines.append(f"  {'':<10} angle    {_fmt_err(block['angle_deg'], 'deg')}")
    gt_ref = pipe.datasets[pipe.reference].ground_truth
    lines.append("parked queries (point mode): estimated vs ground truth")
    for name, ds in pipe.datasets.items():
        summary = art("report", "summary", name)
        if name == pipe.reference or summary is None:
            continue
        d = summary["distance_m"]["median"]
        phi = summary.get("heading_error_deg_signed", None)
        reloc = art("report", "relocalization", name)
        if reloc is not None and len(reloc):
            phi = float(reloc["heading_error_deg"].iloc[0])
        text = f"  {name}: D = {d:.4f} m, phi = {phi:+.2f} deg"
        if gt_ref is not None and ds.ground_truth is not None:
            truth = truth_d_phi(gt_ref, ds.ground_truth, pipe.params_for("report", name).plane)
            text += (
                f"   | truth D = {truth['distance_m']:.4f} m, "
                f"phi = {truth['heading_error_deg']:+.2f} deg"
                f"   | error {abs(d - truth['distance_m']) * 1000:.1f} mm, "
                f"{abs(phi - truth['heading_error_deg']):.2f} deg"
            )
        lines.append(text)
    lines.append("files:")
    for ds, f in written.items():
        lines.append(f"  {ds:<10} {f}")
    lines.append(f"pipeline: {pipe.path}   (rerun: tagtrail run -p {pipe.path})")
    return "\n".join(lines)


def dumps(obj: Any) -> str:
    return json.dumps(obj, indent=2, sort_keys=True)

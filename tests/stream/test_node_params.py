"""The live nodes read their stage parameters from pipeline.yaml (``--pipeline``, ``--dataset``),
else take the stages' defaults; flags override. Checked on what the nodes publish: a tag size
changes ``stream localize``'s poses (vs the simulator's ground truth), a plane changes
``stream relocalize``'s D (vs the offline report stage); real zenoh on 127.0.0.1."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tagtrail.errors import SpecError
from tagtrail.io.layouts import read_tag_map, read_trajectory, write_trajectory_csv
from tagtrail.sim.simulate import simulate
from tagtrail.stages import align as align_stage
from tagtrail.stages import report as report_stage
from tagtrail.stream import cli, codec
from tagtrail.stream.localize import Localizer
from tagtrail.stream.params import stage_params
from tagtrail.stream.replay import bag_messages
from tests.stream.cases import query_frame, reference_frame
from tests.stream.helpers import Collector, free_port, localize_replayed, loopback, running

TAG_SIZE = 0.2  # the simulated tags' edge (m); pnp's default is 0.16
N_FRAMES = 20


@pytest.fixture(scope="module")
def rec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate(
        "circle",
        tmp_path_factory.mktemp("params"),
        frames=N_FRAMES,
        detections=True,
        corner_noise_px=0.0,
        tag_size_m=TAG_SIZE,
        seed=2,
    )["circle"]


def _pipeline(path: Path, source: Path, stages: str, datasets: str = "") -> Path:
    path.write_text(
        f"reference: ref\ndatasets:\n  ref:\n    source: {source}\n{datasets}stages:\n{stages}"
    )
    return path


def _errors_m(poses: list[bytes], gt: pd.DataFrame) -> np.ndarray:
    g = gt.set_index("t_ns")
    out = []
    for raw in poses:
        p = codec.decode_pose(raw)
        row = g.loc[p.sec * 1_000_000_000 + p.nanosec]
        out.append(np.linalg.norm([p.x - row.x_m, p.y - row.y_m, p.z - row.z_m]))
    return np.asarray(out)


def _localize_offline(rec: Path, argv: list[str]) -> np.ndarray:
    """Position errors (m) of the node's handlers, parameters as ``stream localize argv``."""
    ns = cli.build_parser().parse_args(["localize", "--map", str(rec), *argv])
    # the CSV map has no sizes: the tag size comes from the parameters
    loc = Localizer(read_tag_map(rec / "ground_truth" / "tag_map.csv")[0], cli.localize_params(ns))
    out = []
    msgs = bag_messages(rec, ["/camera_info", "/detections"])
    for key, payload in zip(msgs.keys, msgs.payloads, strict=True):
        if key == "camera_info":
            loc.on_camera_info(payload)
        elif loc.camera is not None:
            out += [p for _, p in loc.on_detections(payload)]
    assert len(out) >= N_FRAMES - 1
    return _errors_m(out, read_trajectory(rec / "ground_truth" / "trajectory.csv"))


def test_tag_size_from_the_pipeline_or_the_flag(
    rec: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # no pipeline.yaml here
    assert _localize_offline(rec, []).min() > 0.05  # pnp's default 0.16 m: poses scaled
    assert _localize_offline(rec, ["--tag-size", str(TAG_SIZE)]).max() < 1e-6
    pipe = _pipeline(tmp_path / "lab.yaml", rec, f"  pnp:\n    tag_size: {TAG_SIZE}\n")
    assert _localize_offline(rec, ["--pipeline", str(pipe)]).max() < 1e-6
    assert _localize_offline(rec, ["--pipeline", str(pipe), "--tag-size", "0.16"]).min() > 0.05
    # ./pipeline.yaml is the default pipeline; a dataset's params: override the stages'
    _pipeline(
        tmp_path / "pipeline.yaml",
        rec,
        f"  pnp:\n    tag_size: {TAG_SIZE}\n",
        f"  other:\n    source: {rec}\n    params:\n      pnp:\n        tag_size: 0.1\n",
    )
    assert _localize_offline(rec, []).max() < 1e-6
    assert stage_params(["pnp"], None, "other")["pnp"].tag_size == 0.1
    assert _localize_offline(rec, ["--dataset", "other"]).min() > 0.05


def test_localize_node_publishes_with_the_pipeline_tag_size(rec: Path, tmp_path: Path) -> None:
    pipe = _pipeline(tmp_path / "lab.yaml", rec, f"  pnp:\n    tag_size: {TAG_SIZE}\n")
    port = free_port()
    node_args = [
        "localize",
        "--map",
        rec / "ground_truth" / "tag_map.csv",
        "--pipeline",
        pipe,
        "--listen",
        loopback(port),
        "--duration",
        "45",
        "--stats-period",
        "0",
    ]
    poses, _ = localize_replayed(node_args, rec, port, N_FRAMES - 1)
    err = _errors_m(poses, read_trajectory(rec / "ground_truth" / "trajectory.csv"))
    assert err.max() < 1e-6, err.max()


def test_relocalize_node_publishes_in_the_pipeline_plane(tmp_path: Path) -> None:
    ref, query = reference_frame(200), query_frame(40, out_of_order=False)
    write_trajectory_csv(tmp_path / "reference" / "trajectory.csv", ref)
    write_trajectory_csv(tmp_path / "query" / "trajectory.csv", query)
    ref_f, q_f = read_trajectory(tmp_path / "reference"), read_trajectory(tmp_path / "query")

    def offline(plane: str) -> pd.DataFrame:
        none = align_stage.alignment_block("none", None, 0, 2)
        return report_stage.run(
            q_f, ref_f, none, report_stage.Params(mode="trajectory", plane=plane)
        )["relocalization"].set_index("t_ns")

    want, auto = offline("xy"), offline("auto")
    assert np.abs(want["distance_m"] - auto["distance_m"]).max() > 0.05  # the plane matters
    pipe = _pipeline(tmp_path / "lab.yaml", tmp_path / "reference", "  report:\n    plane: xy\n")
    port = free_port()
    node_args = [
        "relocalize",
        "--reference",
        tmp_path / "reference",
        "--pipeline",
        pipe,
        "--prefix",
        "p",
        "--listen",
        loopback(port),
        "--duration",
        "45",
        "--stats-period",
        "0",
    ]
    with running(node_args) as (node,):
        node.wait_for("relocalize: ready")
        sub = Collector(port, ["p/state"])
        try:
            with running(
                [
                    "replay",
                    tmp_path / "query",
                    "--rate",
                    "0",
                    "--connect",
                    loopback(port),
                    "--wait",
                    "10",
                ]
            ) as (rep,):
                assert rep.p.wait(30) == 0, rep.output
            states = [json.loads(b) for b in sub.wait("p/state", len(query))]
        finally:
            sub.close()
        assert node.stop() == 0, node.output
    t_ns = [s["stamp_sec"] * 1_000_000_000 + s["stamp_nanosec"] for s in states]
    np.testing.assert_allclose(
        [s["distance_m"] for s in states], want.loc[t_ns, "distance_m"], rtol=0, atol=1e-9
    )


def test_parameter_errors_are_spec_errors(
    rec: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SpecError, match="--dataset ref: there is no pipeline file"):
        stage_params(["report"], None, "ref")
    assert stage_params(["report"])["report"] == report_stage.Params()  # no file: defaults
    pipe = _pipeline(tmp_path / "lab.yaml", rec, "  report:\n    plane: xy\n")
    with pytest.raises(SpecError, match="has no such dataset — did you mean 'ref'"):
        stage_params(["report"], pipe, "reff")
    bad = _pipeline(tmp_path / "bad.yaml", rec, "  pnp:\n    tag_siz: 0.2\n")
    with pytest.raises(SpecError, match="unknown key 'tag_siz' — did you mean 'tag_size'"):
        stage_params(["pnp"], bad)
    # as the user sees it: one error line, exit 2, before any port is opened
    assert (
        cli.main(
            [
                "localize",
                "--map",
                str(rec / "ground_truth"),
                "--pipeline",
                str(bad),
                "--connect",
                "tcp/127.0.0.1:1",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "tag_siz" in err[0], err


@pytest.mark.parametrize(("word", "value"), [("edges", "edges"), ("false", False), ("true", True)])
def test_refit_corners_flag_over_the_pipeline(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, word: str, value: object
) -> None:
    """``--refit-corners`` sets the images' corner re-fit over ``extract.refit_corners``."""
    monkeypatch.chdir(tmp_path)
    _pipeline(tmp_path / "pipeline.yaml", tmp_path, "  extract:\n    refit_corners: false\n")
    ns = cli.build_parser().parse_args(["localize", "--map", "m.yaml"])
    assert cli.localize_params(ns).extract.refit_corners is False
    ns = cli.build_parser().parse_args(["localize", "--map", "m.yaml", "--refit-corners", word])
    got = cli.localize_params(ns).extract
    assert got.refit_corners == value and got.detector().refit_corners == value

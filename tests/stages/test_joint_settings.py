"""One settings model for the joint solve (``optimize.joint``), taken by ``trajectory`` from the
map's report; old keys refused in one line; a parked query decides no prior on its own data."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import yaml
from pydantic import BaseModel

from tagtrail.cli import main
from tagtrail.geometry.joint import JointSettings
from tagtrail.geometry.se3 import T_from_xyz_quat
from tagtrail.io.layouts import read_ground, read_trajectory
from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.sim import simulate
from tagtrail.stages import REGISTRY, optimize, trajectory
from tests.cli_helpers import one_error_line

QUERY = {
    "trajectory.tag_map": "reference:optimize.tag_map",
    "trajectory.map_report": "reference:optimize.report",
    "align.tag_map": "reference:optimize.tag_map",
}


def settable(model: type[BaseModel], nested: tuple[type[BaseModel], ...]) -> int:
    """Fields a user can set; a field holding one of the ``nested`` settings models counts as
    many as it has."""
    n = 0
    for f in model.model_fields.values():
        sub = next((m for m in nested if f.annotation is m), None)
        n += settable(sub, nested) if sub is not None else 1
    return n


def test_the_settings_are_few_and_set_once() -> None:
    """optimize: 12 (the joint solve's 6 among them; ``survey`` counted once, as the issue's 27
    did); trajectory: 6, none of them the joint solve's (it takes the map's)."""
    assert settable(optimize.Params, (JointSettings,)) <= 12
    assert settable(trajectory.Params, (JointSettings,)) <= 6
    assert len(JointSettings.model_fields) == 6
    assert not set(JointSettings.model_fields) & set(trajectory.Params.model_fields)


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The room: a 4 s reference drive and a parked 1 s query, from detections."""
    root = tmp_path_factory.mktemp("joint")
    simulate("room", root / "data", frames=120, query_frames=30, detections=True)
    doc = {
        "reference": "reference",
        "datasets": {
            "reference": {"source": str(root / "data" / "reference")},
            "query_1": {"source": str(root / "data" / "query_1"), "inputs": QUERY},
            # wired as before issue 27: the map from the reference, the settings its own
            "query_2": {
                "source": str(root / "data" / "query_2"),
                "inputs": {k: v for k, v in QUERY.items() if "map_report" not in k},
            },
        },
        "stages": {"pnp": {"tag_size": 0.16}},
    }
    (root / "pipeline.yaml").write_text(yaml.safe_dump(doc))
    return root


@pytest.mark.parametrize(
    ("key", "where"),
    [
        (
            "optimize.motion_acc_sigma=0.2",
            "optimize.motion_acc_sigma is no longer a setting: use optimize.joint.motion",
        ),
        (
            "trajectory.ground=none",
            "trajectory.ground is no longer a setting: use "
            "optimize.joint.ground; trajectory takes the map's settings",
        ),
        (
            "optimize.ba_loss=huber",
            "optimize.ba_loss is no longer a setting: the corners' loss is fixed",
        ),
    ],
)
def test_an_old_key_is_refused_in_one_line_naming_its_place(
    project: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    key: str,
    where: str,
) -> None:
    monkeypatch.chdir(project)
    assert main(["status", "-S", key]) == 2
    assert where in one_error_line(capsys)


def test_a_parked_query_takes_the_maps_decisions_and_says_so(
    project: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The reference (4 s of driving) decides the ground plane and the wheeled drive on its own
    data; the parked query's own map decides neither (the log and its report say why), and its
    trajectory, solved against the reference's map under its settings, takes the reference's
    decisions. A query wired the old way (its own report beside the reference's map) is told."""
    monkeypatch.chdir(project)
    with caplog.at_level(logging.INFO, logger="tagtrail"):
        assert main(["run"]) == 0
    runner = Runner(load_pipeline(project / "pipeline.yaml", REGISTRY))
    keys = {(s.stage, s.dataset): s.key for s in runner.plan()}
    ref = runner.store.load("optimize", keys["optimize", "reference"], "report")
    own = runner.store.load("optimize", keys["optimize", "query_1"], "report")
    assert ref.joint == JointSettings() and ref.bundle.ground.note == ""
    assert not own.bundle.ground.applied and "parked" in own.bundle.ground.note
    lines = [r.getMessage() for r in caplog.records if r.name.endswith("stages.trajectory")]
    said = [m for m in lines if "the reference's decision" in m]
    assert len(said) == 1 and "parked" in said[0]
    assert said[0].startswith(
        "trajectory: whether the camera moves in one plane like a robot's "
        "is not decided on this data: the camera moved"
    )
    assert ref.bundle.ground.applied == ("held to one plane at a fixed tilt" in said[0])
    warned = [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and "is it the map's?" in r.getMessage()
    ]
    assert len(warned) == 1 and "trajectory.map_report: reference:optimize.report" in warned[0]
    assert any(
        r.getMessage().startswith(
            "optimize: whether the camera moves in one plane like a "
            "robot's is not decided on this data: the camera moved"
        )
        and r.getMessage().endswith("too little to decide on; held to neither")
        for r in caplog.records
    )


def test_the_reference_exports_the_ground_plane_its_trajectory_keeps_to(
    project: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``ground.json`` (what ``stream localize --smooth`` holds from the first frame): the
    plane and mount of the report's ground block, read back by the live node's reader; the
    exported trajectory's camera centres sit on it and its cameras see its normal where it
    says. The parked query, whose own map decided no plane, exports none."""
    monkeypatch.chdir(project)
    assert main(["run"]) == 0
    runner = Runner(load_pipeline(project / "pipeline.yaml", REGISTRY))
    keys = {(s.stage, s.dataset): s.key for s in runner.plan()}
    ref = runner.store.load("optimize", keys["optimize", "reference"], "report")
    out = project / "outputs"
    g = read_ground(out / "reference")
    assert ref.bundle.ground.applied and g == ref.bundle.ground.known()
    assert g.forward_camera is not None and g.lever_m is not None  # a wheeled robot's
    assert not (out / "query_1" / "ground.json").exists()
    tr = read_trajectory(out / "reference" / "trajectory.csv")
    T = T_from_xyz_quat(
        tr[["x_m", "y_m", "z_m"]].to_numpy(), tr[["qx", "qy", "qz", "qw"]].to_numpy()
    )
    n, u = np.array(g.normal), np.array(g.normal_camera)
    heights = T[:, :3, 3] @ n - g.offset_m
    assert np.sqrt(np.mean(heights**2)) < 0.002, heights
    seen = np.einsum("fji,j->fi", T[:, :3, :3], n)  # the normal in each camera's frame
    assert np.degrees(np.arccos(np.clip(seen @ u, -1, 1))).max() < 0.5
    assert abs(np.dot(np.array(g.forward_camera), u)) < 1e-9  # across the normal

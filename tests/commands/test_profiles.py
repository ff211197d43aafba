"""Profiles: `tagtrail init --profile` writes their topics and parameters into pipeline.yaml
(visible, overridable, accepted by `tagtrail run`); the live nodes take the same --profile."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from tagtrail.cli import main
from tagtrail.runner.spec import load_pipeline
from tagtrail.schemas.profiles import PROFILES, get_profile
from tagtrail.sim import bagwrite
from tagtrail.sim.scenarios import SimOptions
from tagtrail.sim.simulate import simulate
from tagtrail.stages import REGISTRY
from tagtrail.stream import cli as stream_cli
from tagtrail.stream.params import stage_params
from tests.cli_helpers import one_error_line


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory, room_bags: Path) -> Path:
    root = tmp_path_factory.mktemp("profile_bags")
    shutil.copytree(room_bags, root / "det")
    simulate("room", root / "jpeg", frames=20, query_frames=4, compressed=True)
    return root


def test_every_profile_is_valid_and_matches_what_it_names() -> None:
    for p in PROFILES.values():
        for stage, params in p.stages.items():
            REGISTRY[stage].Params(**params)  # a file `tagtrail run` accepts
        assert dict(p.record).keys() >= set(p.topics.values())
        assert p.live.camera_info_key == p.topics["camera_info"].lstrip("/")
    # the simulator writes what the profiles say
    assert PROFILES["limo"].topics == {
        "detections": bagwrite.DETECTIONS_TOPIC,
        "camera_info": bagwrite.DETECTIONS_INFO_TOPIC,
    }
    assert PROFILES["limo-images"].topics["image"] == bagwrite.IMAGE_TOPIC
    assert PROFILES["sim"].topics == {
        "image": bagwrite.COMPRESSED_TOPIC,
        "camera_info": bagwrite.INFO_TOPIC,
    }
    assert PROFILES["sim"].stages["pnp"]["tag_size"] == SimOptions().tag_size_m


def test_init_writes_the_profile_into_the_file(
    bags: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "pipeline.yaml"
    assert (
        main(
            [
                "init",
                "--profile",
                "limo",
                "--reference",
                str(bags / "det" / "reference"),
                "--query",
                str(bags / "det" / "query_1"),
                "--tag-size",
                "0.16",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    text = out.read_text()
    assert "# Profile limo:" in text
    doc = yaml.safe_load(text)
    assert doc["datasets"]["reference"]["topics"] == {
        "detections": "/detections",
        "camera_info": "/camera_info",
    }
    assert doc["datasets"]["query"]["topics"] == doc["datasets"]["reference"]["topics"]
    assert doc["stages"] == {"pnp": {"tag_size": 0.16}, "report": {"plane": "xz"}}
    pipe = load_pipeline(out, REGISTRY)
    assert pipe.params_for("report", "reference").plane == "xz"
    # overridable: a flag over the profile, and the file is an ordinary one to edit
    assert (
        main(
            [
                "init",
                "--profile",
                "sim",
                "--reference",
                str(bags / "jpeg" / "reference"),
                "--tag-size",
                "0.2",
                "-o",
                str(out),
                "--force",
            ]
        )
        == 0
    )
    doc = yaml.safe_load(out.read_text())
    assert doc["stages"]["pnp"]["tag_size"] == 0.2
    assert doc["datasets"]["reference"]["topics"]["image"] == bagwrite.COMPRESSED_TOPIC
    capsys.readouterr()
    # a profile whose topics the recording lacks: one line naming topic and profile
    assert (
        main(
            [
                "init",
                "--profile",
                "limo",
                "--reference",
                str(bags / "jpeg" / "reference"),
                "--tag-size",
                "0.16",
                "-o",
                str(out),
                "--force",
            ]
        )
        == 2
    )
    line = one_error_line(capsys)
    assert "/detections" in line and "--profile limo" in line


def test_list_profiles(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["init", "--list-profiles"]) == 0
    text = capsys.readouterr().out
    for name, p in PROFILES.items():
        assert f"{name}: {p.description}" in text
    assert "/camera/color/image_raw (Image)" in text
    assert main(["init", "-o", "x.yaml"]) == 2
    assert "--reference" in one_error_line(capsys)


def test_live_nodes_take_the_profile(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # no pipeline.yaml here: the profile's parameters apply
    parse = stream_cli.build_parser().parse_args
    ns = stream_cli.with_profile(parse(["localize", "--map", "m", "--profile", "limo-images"]))
    assert (ns.image_key, ns.image_type, ns.camera_info_key, ns.pose_key) == (
        "camera/color/image_raw",
        "raw",
        "camera/color/camera_info",
        "tag_only_pose",
    )
    ns = stream_cli.with_profile(
        parse(["localize", "--map", "m", "--profile", "limo", "--camera-info-key", "cam/info"])
    )
    assert (ns.image_key, ns.detections_key, ns.camera_info_key) == (
        None,
        "detections",
        "cam/info",
    )  # flag wins
    assert ns.camera_forward_m == 0.084  # the LIMO's camera ahead of its base (the smoother's)
    ns = stream_cli.with_profile(
        parse(["localize", "--map", "m", "--profile", "limo", "--camera-forward", "0.1"])
    )
    assert ns.camera_forward_m == 0.1
    ns = stream_cli.with_profile(parse(["localize", "--map", "m", "--camera-forward", "-0.05"]))
    assert ns.camera_forward_m == -0.05  # a camera behind the turning centre
    ns = stream_cli.with_profile(parse(["localize", "--map", "m"]))  # no profile: as before
    assert (ns.detections_key, ns.camera_info_key, ns.image_type) == (
        "detections",
        "camera_info",
        "compressed",
    )
    assert ns.camera_forward_m is None  # unknown: fitted once the drive has turned
    assert stage_params(["report"], profile="limo")["report"].plane == "xz"
    assert stage_params(["report"])["report"].plane == "auto"
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("{}")
    ns = stream_cli.with_profile(parse(["replay", str(bag), "--profile", "sim"]))
    assert ns.topics == [t for t, _ in PROFILES["sim"].record]
    ns = stream_cli.with_profile(parse(["relocalize", "--reference", "r", "--profile", "sim"]))
    assert ns.pose_key == "tag_only_pose"
    with pytest.raises(Exception, match="unknown profile"):
        get_profile("limo2")


def test_limo_profiles_record_the_wheel_odometry_when_there_is_some() -> None:
    """The LIMO publishes /odom: its profiles record it (the odometry prior's input) and
    `stream localize --smooth --profile limo` subscribes to it; replay takes it when a bag has
    it (optional: bags of the original workflow have none)."""
    from tagtrail.stream import cli

    for name in ("limo", "limo-images"):
        p = PROFILES[name]
        assert ("/odom", "nav_msgs/msg/Odometry") in p.record and p.optional == ("/odom",)
        ns = cli.with_profile(
            cli.build_parser().parse_args(["localize", "--map", "m.yaml", "--profile", name])
        )
        assert ns.odom_key == "odom"
    ns = cli.with_profile(cli.build_parser().parse_args(["localize", "--map", "m.yaml"]))
    assert ns.odom_key is None

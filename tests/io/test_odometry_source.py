"""Reading wheel odometry and the static mount: ``Source.odometry()`` / ``static_frames()`` of
bags (simulated by ``tagtrail simulate``, written in tmp_path, ROS 1 with TagSLAM's real
odometry), the topic choice, bad odometry, and extract's ``odometry`` / ``mount`` outputs."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer

from tagtrail.cli import main
from tagtrail.errors import SourceError
from tagtrail.geometry.frames import chain
from tagtrail.geometry.se3 import T_from_xyz_quat, inv
from tagtrail.io import msgs
from tagtrail.io.sources import open_source
from tagtrail.schemas.artifacts import SCHEMAS, columns, conform
from tagtrail.schemas.documents import MountDoc
from tagtrail.schemas.pipeline import DatasetConfig, Topics
from tagtrail.sim import simulate
from tagtrail.sim.camera import FRAME_ID, limo_camera
from tagtrail.stages import extract
from tests.extracting import extract_from
from tests.io import bags

T0 = bags.T0_NS
ODOM = "nav_msgs/msg/Odometry"
COLS = columns("extract.odometry")
PLACEHOLDER = np.diag([0.1, 0.1, 0.1, 1.0, 1.0, 1.0]).reshape(-1)


def odom_msg(
    t_ns: int,
    xy_yaw: tuple[float, float, float] = (0.0, 0.0, 0.0),
    cov: np.ndarray = PLACEHOLDER,
    child: str = "base_link",
) -> Any:
    t = msgs.typestore().types
    x, y, yaw = xy_yaw
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
        ),
    )
    V3 = t["geometry_msgs/msg/Vector3"]
    return t[ODOM](
        header=bags.header(t_ns, "odom"),
        child_frame_id=child,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.asarray(cov)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](
                linear=V3(x=0.3, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.1)
            ),
            covariance=np.zeros(36),
        ),
    )


def tf_msg(edges: list[tuple[str, str, list[float]]], t_ns: int = T0) -> Any:
    t = msgs.typestore().types
    out = []
    for parent, child, v in edges:
        out.append(
            t["geometry_msgs/msg/TransformStamped"](
                header=bags.header(t_ns, parent),
                child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](x=v[0], y=v[1], z=v[2]),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=v[3], y=v[4], z=v[5], w=v[6]),
                ),
            )
        )
    return t["tf2_msgs/msg/TFMessage"](transforms=out)


def frames_bag(
    path: Path, extra: list[tuple[str, int, Any]], n: int = 5, garbage: tuple[int, ...] = ()
) -> Path:
    """A detections bag (``n`` frames at 10 Hz, one tag, CameraInfo frame ``camera``) plus
    ``extra`` messages; the ``/odom`` messages at the indices ``garbage`` (of ``extra``) are
    written as bytes that do not deserialize."""
    cam = limo_camera()
    corners = np.array([[300.0, 200.0], [340.0, 200.0], [340.0, 240.0], [300.0, 240.0]])
    out: list[tuple[str, int, Any]] = []
    for k in range(n):
        t = T0 + k * 100_000_000
        out.append(("/camera_info", t, bags.camera_info_msg(cam, t)))
        out.append(("/detections", t, bags.detections_msg(t, [(0, 0, 80.0, corners)])))
    bad = {id(extra[i][2]) for i in garbage}
    ts = msgs.typestore()
    with Writer(path, version=9) as w:
        conns: dict[str, Any] = {}
        for topic, t, msg in sorted(out + extra, key=lambda m: m[1]):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msg.__msgtype__, typestore=ts)
            raw = (
                b"\x00\x01\x00\x00\x07"
                if id(msg) in bad
                else ts.serialize_cdr(msg, msg.__msgtype__)
            )
            w.write(conns[topic], t, raw)
    return path


def odoms(topic: str, n: int = 10, child: str = "base_link") -> list[tuple[str, int, Any]]:
    return [
        (
            topic,
            T0 + k * 20_000_000,
            odom_msg(T0 + k * 20_000_000, (0.01 * k, 0.0, 0.0), child=child),
        )
        for k in range(n)
    ]


def cfg(source: Path, **topics: str) -> DatasetConfig:
    return DatasetConfig(source=source, topics=Topics(**topics))


# --- simulated recordings ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("odomsrc")
    return simulate("circle", out, frames=40, detections=True, seed=1)["circle"]


def test_simulated_odometry_read_as_recorded(sim_bag: Path) -> None:
    out = extract_from(sim_bag)
    odo, mount = out["odometry"], out["mount"]
    assert list(odo.columns) == COLS
    table = conform("extract.odometry", odo)
    assert table.schema.equals(SCHEMAS["extract.odometry"])
    truth = pd.read_csv(sim_bag / "ground_truth" / "odometry_truth.csv")
    np.testing.assert_array_equal(odo["t_ns"], truth["t_ns"])  # header stamps = publication
    with AnyReader([sim_bag], default_typestore=msgs.typestore()) as r:
        conns = [c for c in r.connections if c.topic == "/odom"]
        want = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns)]
    assert len(want) == len(odo) > 60
    k = len(want) // 2
    m = want[k]
    p, q = m.pose.pose.position, m.pose.pose.orientation
    np.testing.assert_array_equal(
        odo.loc[k, COLS[1:11]].to_numpy(float),
        [p.x, p.y, p.z, q.x, q.y, q.z, q.w, m.twist.twist.linear.x, 0.0, m.twist.twist.angular.z],
    )
    np.testing.assert_array_equal(
        odo[["var_x_m2", "var_y_m2", "var_yaw_rad2"]].iloc[0], [0.1, 0.1, 1]
    )
    assert isinstance(mount, MountDoc)
    assert (mount.odom_frame, mount.base_frame, mount.camera_frame) == (
        "odom",
        "base_link",
        FRAME_ID,
    )
    assert mount.source == "tf_static" and mount.topic == "/odom"
    assert mount.covariance == "constant"  # the LIMO's placeholder
    scene = yaml.safe_load((sim_bag / "ground_truth" / "scene.yaml").read_text())
    assert mount.base_T_camera is not None
    np.testing.assert_allclose(mount.base_T_camera, scene["base_T_camera"], atol=1e-12)


def test_extract_stores_odometry_and_mount(
    sim_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``tagtrail run extract``: both artifacts stored, the table in its schema, the document
    as its model."""
    monkeypatch.chdir(tmp_path)
    spec = {"reference": "circle", "datasets": {"circle": {"source": str(sim_bag)}}}
    (tmp_path / "pipeline.yaml").write_text(yaml.safe_dump(spec))
    assert main(["run", "extract"]) == 0
    (table,) = (tmp_path / "artifacts").rglob("*odometry*.parquet")
    df = pd.read_parquet(table)
    assert list(df.columns) == COLS and len(df) > 60 and df["t_ns"].dtype == np.int64
    (doc,) = (tmp_path / "artifacts").rglob("*mount*.json")
    mount = MountDoc.model_validate_json(doc.read_text())
    assert mount.base_frame == "base_link" and mount.base_T_camera is not None


def test_sources_without_odometry(tmp_path: Path) -> None:
    obs = simulate("observations", tmp_path, frames=10)["observations"]
    with open_source(cfg(obs)) as src:
        assert src.odometry() is None and src.static_frames().transforms == ()
    out = extract_from(obs)
    assert list(out["odometry"].columns) == COLS and out["odometry"].empty
    assert out["mount"] == MountDoc()
    off = simulate("circle", tmp_path / "off", frames=10, detections=True, odom=False)["circle"]
    out = extract_from(off)
    assert out["odometry"].empty and out["mount"].base_T_camera is None


# --- topic choice ----------------------------------------------------------------------------


def test_auto_topic_prefers_odom_and_finds_the_limo_remap(tmp_path: Path) -> None:
    one = frames_bag(tmp_path / "one", odoms("/wheel/odom"))
    with open_source(cfg(one)) as src:
        odo = src.odometry()
        assert odo is not None and odo.topic == "/wheel/odom" and len(odo.rows) == 10
        assert (odo.frame_id, odo.child_frame_id) == ("odom", "base_link")
    both = frames_bag(tmp_path / "both", odoms("/wheel/odom", 4) + odoms("/odom", 7))
    with open_source(cfg(both)) as src:
        odo = src.odometry()
        assert odo is not None and odo.topic == "/odom" and len(odo.rows) == 7
    with open_source(cfg(both, odometry="/wheel/odom")) as src:
        odo = src.odometry()
        assert odo is not None and odo.topic == "/wheel/odom" and len(odo.rows) == 4
    for off in ("none", "", "None"):
        with open_source(cfg(both, odometry=off)) as src:
            assert src.odometry() is None
        assert extract_from(cfg(both, odometry=off))["odometry"].empty
    with pytest.raises(SourceError, match="topic /nope .*topics.odometry"):
        open_source(cfg(both, odometry="/nope"))
    with pytest.raises(SourceError, match="has type .* not nav_msgs/msg/Odometry"):
        open_source(cfg(both, odometry="/camera_info"))


def test_ambiguous_odometry_is_one_error_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = frames_bag(tmp_path / "two", odoms("/wheel/odom", 3) + odoms("/odom_raw", 3))
    with pytest.raises(SourceError) as err:
        open_source(cfg(bag))
    text = str(err.value)
    assert "/odom_raw" in text and "/wheel/odom" in text and "topics: {odometry:" in text
    monkeypatch.chdir(tmp_path)
    spec = {"reference": "two", "datasets": {"two": {"source": "two"}}}
    (tmp_path / "pipeline.yaml").write_text(yaml.safe_dump(spec))
    capsys.readouterr()
    assert main(["run", "extract"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "several odometry" in lines[0]
    spec["datasets"]["two"]["topics"] = {"odometry": "/odom_raw"}  # type: ignore[index]
    (tmp_path / "pipeline.yaml").write_text(yaml.safe_dump(spec))
    assert main(["run", "extract"]) == 0


# --- bad odometry ------------------------------------------------------------------------------


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


@pytest.mark.parametrize(
    ("case", "expect"),
    [
        ("nan", "2 not finite"),
        ("back", "2 stamps going back"),
        ("single", "a single message"),
        ("zero_cov", "10 no usable covariance"),
        ("unknown_cov", "10 no usable covariance"),
        ("garbage", "2 unreadable (left out)"),
    ],
)
def test_bad_odometry_one_warning_no_crash(
    case: str, expect: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rows = odoms("/odom")
    if case == "nan":
        rows[3] = ("/odom", rows[3][1], odom_msg(rows[3][1], (math.nan, 0.0, 0.0)))
        rows[6] = ("/odom", rows[6][1], odom_msg(rows[6][1], (0.0, math.inf, 0.0)))
    elif case == "back":  # header stamps out of order (recorded in order)
        rows[4] = ("/odom", rows[4][1], odom_msg(rows[4][1] - 60_000_000))
        rows[8] = ("/odom", rows[8][1], odom_msg(rows[7][1]))
    elif case == "single":
        rows = rows[:1]
    elif case == "garbage":
        pass
    else:
        cov = np.zeros(36) if case == "zero_cov" else np.diag([1e6] * 6).reshape(-1)
        rows = [(tp, t, odom_msg(t, cov=cov)) for tp, t, _ in rows]
    garbage = (2, 5) if case == "garbage" else ()
    bag = frames_bag(tmp_path / case, rows, garbage=garbage)
    with caplog.at_level(logging.INFO):
        out = extract_from(bag)
    odo = out["odometry"]
    assert len(odo) == len(rows) - len(garbage)  # kept: the prior decides
    warns = [w for w in _warnings(caplog) if "odometry" in w]
    assert len(warns) == 1 and "/odom" in warns[0] and expect in warns[0], warns
    if case in ("zero_cov", "unknown_cov"):
        assert odo[["var_x_m2", "var_y_m2", "var_yaw_rad2"]].isna().all().all()
        assert out["mount"].covariance == "unusable"
    if case == "nan":
        assert np.isnan(odo.loc[3, "x_m"]) and not np.isfinite(odo.loc[6, "y_m"])


def test_clean_odometry_gives_no_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    bag = frames_bag(tmp_path / "clean", odoms("/odom"))
    with caplog.at_level(logging.INFO):
        extract_from(bag)
    assert not [w for w in _warnings(caplog) if "odometry" in w]


# --- static transforms -------------------------------------------------------------------------


def test_tf_static_chain_composes_through_intermediate_frames(tmp_path: Path) -> None:
    """base_link → camera_link → camera (CameraInfo's frame), written as two transforms in one
    message, composes to their product; an unrelated tree leaves the mount unknown."""
    s = math.sqrt(0.5)
    link = [0.1, 0.02, 0.2, 0.0, 0.0, math.sin(0.1), math.cos(0.1)]
    optical = [0.0, 0.01, 0.0, -0.5, 0.5, -0.5, 0.5]
    tfs = [("base_link", "camera_link", link), ("camera_link", "camera", optical)]
    bag = frames_bag(tmp_path / "tf", [*odoms("/odom"), ("/tf_static", T0, tf_msg(tfs))])
    with open_source(cfg(bag)) as src:
        frames = src.static_frames()
        assert frames.camera_frame == "camera" and len(frames.transforms) == 2
    mount = extract_from(bag)["mount"]
    want = T_from_xyz_quat(link[:3], link[3:]) @ T_from_xyz_quat(optical[:3], optical[3:])
    got = T_from_xyz_quat(mount.base_T_camera[:3], mount.base_T_camera[3:])
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert mount.source == "tf_static"
    other = [("base_link", "laser", [0, 0, 0.3, 0, 0, s, s]), ("map", "camera", optical)]
    bag = frames_bag(tmp_path / "other", [*odoms("/odom"), ("/tf_static", T0, tf_msg(other))])
    mount = extract_from(bag)["mount"]
    assert mount.base_T_camera is None and mount.source is None and mount.camera_frame == "camera"


def test_chain_runs_up_and_down_the_tree() -> None:
    rng = np.random.default_rng(0)

    def rand_T() -> np.ndarray:
        q = rng.normal(size=4)
        return T_from_xyz_quat(rng.normal(size=3), q / np.linalg.norm(q))

    root_T_base, root_T_cam, cam_T_opt = rand_T(), rand_T(), rand_T()
    edges = [("root", "base", root_T_base), ("/root", "cam", root_T_cam), ("cam", "opt", cam_T_opt)]
    got = chain(edges, "base", "opt")
    assert got is not None
    np.testing.assert_allclose(got, inv(root_T_base) @ root_T_cam @ cam_T_opt, atol=1e-12)
    np.testing.assert_allclose(chain(edges, "opt", "base"), inv(got), atol=1e-12)
    np.testing.assert_array_equal(chain(edges, "cam", "/cam"), np.eye(4))
    assert chain(edges, "base", "elsewhere") is None


# --- ROS 1: TagSLAM's real odometry ------------------------------------------------------------


def test_ros1_bag_with_real_odometry(realdata: Path, tmp_path: Path) -> None:
    """TagSLAM test 1's real detections and its recorded ``nav_msgs/Odometry`` (both ROS 1,
    copied message for message into one bag): read with its varying covariance."""
    import bz2

    srcs = {}
    for name in ("tag_detections", "reference"):
        f = tmp_path / f"{name}.bag"
        f.write_bytes(
            bz2.decompress((realdata / "tagslam_test_1" / f"{name}.bag.bz2").read_bytes())
        )
        srcs[name] = f
    bag = tmp_path / "merged.bag"
    recorded = []
    with Writer1(bag) as w, AnyReader(list(srcs.values())) as r:
        conns = {}
        for c in r.connections:
            if c.msgtype in (ODOM, msgs.TAGSLAM_DETECTIONS):
                conns[c.topic] = w.add_connection(
                    c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest
                )
        for c, t, raw in r.messages(connections=[c for c in r.connections if c.topic in conns]):
            w.write(conns[c.topic], t, raw)
            if c.msgtype == ODOM:
                recorded.append(r.deserialize(raw, c.msgtype))
    assert len(recorded) == 228
    with open_source(cfg(bag)) as src:
        odo = src.odometry()
        assert odo is not None and odo.topic == "/tagslam/odom/body_rig"
        assert odo.frame_id == "map" and odo.child_frame_id == recorded[0].child_frame_id
        rows = odo.rows
        assert src.static_frames().transforms == ()  # TagSLAM records /tf, no /tf_static
    assert len(rows) == 228
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in recorded]
    np.testing.assert_array_equal(rows["t_ns"], stamps)
    np.testing.assert_array_equal(rows["var_x_m2"], [m.pose.covariance[0] for m in recorded])
    np.testing.assert_array_equal(rows["var_yaw_rad2"], [m.pose.covariance[35] for m in recorded])
    np.testing.assert_array_equal(rows["qw"], [m.pose.pose.orientation.w for m in recorded])
    assert extract.covariance_kind(rows) == "varying"  # a real estimate's covariance

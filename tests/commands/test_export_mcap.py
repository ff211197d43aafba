"""``tagtrail export-mcap`` on real runs of simulated recordings (a detections bag with a parked
query, and an image bag): the MCAP is read back with the ``mcap`` library and every message
decoded by ``mcap_ros2`` from the definitions stored in the file (so they are complete); channels,
schemas and counts are checked against the source bag and the run's exported files (not the code
under test), plus the layout beside it and the one-line errors."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

import tagtrail.cli
from tagtrail.io.bags import open_bag
from tagtrail.io.layouts import read_tag_map, read_trajectory
from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.sim import simulate
from tagtrail.stages import REGISTRY
from tests.cli_helpers import ROOM_QUERY_PIPELINE, one_error_line

Capsys = pytest.CaptureFixture[str]
PIPELINE = ROOM_QUERY_PIPELINE
STATIC = {
    "/tag_map": "visualization_msgs/msg/MarkerArray",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/reference_path": "nav_msgs/msg/Path",
}


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory, room_bags: Path) -> Path:
    """The `room` detection recordings (reference + parked query_1), run end to end."""
    root = tmp_path_factory.mktemp("export_mcap")
    shutil.copytree(room_bags, root / "bags")  # a test moves a recording
    (root / "pipeline.yaml").write_text(PIPELINE)
    assert tagtrail.cli.main(["run", "-p", str(root / "pipeline.yaml")]) == 0
    return root


def export(project: Path, out: Path, *argv: str) -> int:
    return tagtrail.cli.main(
        ["export-mcap", "-p", str(project / "pipeline.yaml"), "-o", str(out), *argv]
    )


def read_mcap(
    path: Path,
) -> tuple[
    Any, dict[str, tuple[str, str, str]], dict[str, list[Any]], dict[str, list[tuple[int, bytes]]]
]:
    """Header, topic → (schema name, schema encoding, message encoding), decoded messages and
    (log time, raw bytes) per topic."""
    decoded: dict[str, list[Any]] = {}
    raw: dict[str, list[tuple[int, bytes]]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        summary = reader.get_summary()
        assert summary is not None
        channels = {
            c.topic: (
                summary.schemas[c.schema_id].name,
                summary.schemas[c.schema_id].encoding,
                c.message_encoding,
            )
            for c in summary.channels.values()
        }
        counts = {
            summary.channels[cid].topic: n
            for cid, n in summary.statistics.channel_message_counts.items()
        }
        for _, ch, msg, dec in reader.iter_decoded_messages(log_time_order=True):
            decoded.setdefault(ch.topic, []).append(dec)
            raw.setdefault(ch.topic, []).append((msg.log_time, msg.data))
    assert counts == {t: len(v) for t, v in decoded.items()}  # the summary says what is there
    return header, channels, decoded, raw


def source_messages(bag: Path) -> dict[str, list[bytes]]:
    reader = open_bag(bag)
    try:
        out: dict[str, list[bytes]] = {}
        for conn, _, data in reader.messages():
            out.setdefault(conn.topic, []).append(bytes(data))
        return out
    finally:
        reader.close()


def artifact(project: Path, stage: str, dataset: str, output: str) -> Any:
    runner = Runner(load_pipeline(project / "pipeline.yaml", REGISTRY))
    key = runner.key_of(stage, dataset)
    assert key is not None
    return runner.store.load(stage, key, output)


def test_reference_export(project: Path, tmp_path: Path, capsys: Capsys) -> None:
    out = tmp_path / "reference.mcap"
    assert export(project, out) == 0
    printed = capsys.readouterr().out
    header, channels, msgs, raw = read_mcap(out)
    assert header.profile == "ros2"
    expected = {
        **STATIC,
        "/tf": "tf2_msgs/msg/TFMessage",
        "/detections/annotations": "foxglove_msgs/msg/ImageAnnotations",
        "/detections": "apriltag_msgs/msg/AprilTagDetectionArray",
        "/camera_info": "sensor_msgs/msg/CameraInfo",
    }
    assert channels == {t: (m, "ros2msg", "cdr") for t, m in expected.items()}
    assert f"wrote {out} [reference]: " in printed

    # the source's messages, copied byte for byte, each once
    src = source_messages(project / "bags" / "reference")
    for topic in ("/detections", "/camera_info"):
        assert [b for _, b in raw[topic]] == src[topic]
    # /tf: world_T_cam of every row of the exported trajectory.csv, at its stamp
    traj = read_trajectory(project / "outputs" / "reference")
    assert [t for t, _ in raw["/tf"]] == traj["t_ns"].tolist()
    tf = [m.transforms[0] for m in msgs["/tf"]]
    assert {(x.header.frame_id, x.child_frame_id) for x in tf} == {
        ("map", "camera_color_optical_frame")
    }  # the source's camera frame
    got = np.array(
        [
            [
                x.transform.translation.x,
                x.transform.translation.y,
                x.transform.translation.z,
                x.transform.rotation.x,
                x.transform.rotation.y,
                x.transform.rotation.z,
                x.transform.rotation.w,
            ]
            for x in tf
        ]
    )
    np.testing.assert_allclose(
        got, traj[["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]], rtol=0, atol=1e-12
    )
    # the map: one square + one id per tag of tag_map.csv, the anchor orange; 3σ spheres
    tags, anchor = read_tag_map(project / "outputs" / "reference" / "tag_map.yaml")
    (arr,) = msgs["/tag_map"]
    squares = {m.id: m for m in arr.markers if m.ns == "tags"}
    assert sorted(squares) == sorted(tags["tag_id"].tolist())
    assert all(m.type == 1 and m.header.frame_id == "map" for m in squares.values())
    for _, row in tags.iterrows():
        p = squares[int(row["tag_id"])].pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], row[["x_m", "y_m", "z_m"]], atol=1e-12)
    orange = {
        i
        for i, m in squares.items()  # ColorRGBA is float32
        if (m.color.r, m.color.g) == (1.0, np.float32(0.55))
    }
    assert orange == {anchor}
    texts = {m.id: m.text for m in arr.markers if m.ns == "tag_ids"}
    assert texts[anchor] == f"tag36h11:{anchor} (anchor)" and len(texts) == len(tags)
    std = artifact(project, "optimize", "reference", "tag_map").set_index("tag_id")["std_pos_m"]
    spheres = {m.id: m.scale.x for m in arr.markers if m.ns == "tag_std_3sigma"}
    assert set(spheres) == {int(i) for i, s in std.items() if np.isfinite(s) and s > 0}
    for i, d in spheres.items():
        assert d == pytest.approx(6 * std[i], rel=1e-12)
    (tfs,) = msgs["/tf_static"]
    assert sorted(x.child_frame_id for x in tfs.transforms) == sorted(
        f"tag36h11:{i}" for i in tags["tag_id"]
    )
    (path,) = msgs["/reference_path"]
    assert len(path.poses) == len(traj) and path.header.frame_id == "map"
    # annotations: one per frame with detections; outlines = corners (+0.5 px: Foxglove's origin
    # is the top-left pixel's corner), ids as text
    dets = artifact(project, "extract", "reference", "detections")
    assert [t for t, _ in raw["/detections/annotations"]] == sorted(dets["t_ns"].unique())
    first = msgs["/detections/annotations"][0]
    d0 = dets[dets["t_ns"] == dets["t_ns"].min()]
    assert [t.text for t in first.texts] == [str(i) for i in d0["tag_id"]]
    np.testing.assert_allclose(
        [[q.x, q.y] for q in first.points[0].points],
        d0.iloc[0][[f"c{i}{a}" for i in range(4) for a in "xy"]].to_numpy(float).reshape(4, 2)
        + 0.5,
        atol=1e-12,
    )
    assert first.points[0].type == 2  # LINE_LOOP
    # every log time in order: static messages first, at the run's first stamp
    times = sorted(t for v in raw.values() for t, _ in v)
    assert all(raw[t][0][0] == times[0] for t in STATIC)

    layout = json.loads((tmp_path / "reference.layout.json").read_text())
    named = set(_topics(layout))
    assert named <= set(channels), named - set(channels)
    assert {"/tag_map", "/detections/annotations", "/camera_info"} <= named


def _topics(doc: Any) -> list[str]:
    """Topic names a Foxglove layout refers to (keys of ``topics``/``annotations``, image and
    calibration topics, plot series' topic part)."""
    out: list[str] = []
    if isinstance(doc, dict):
        for k, v in doc.items():
            if k in ("topics", "annotations"):
                out += list(v)
            elif k in ("imageTopic", "calibrationTopic", "cameraInfoTopic"):
                out.append(v)
            elif k == "value" and isinstance(v, str):
                out.append(v.rsplit(".", 1)[0])
            out += _topics(v)
    elif isinstance(doc, list):
        for v in doc:
            out += _topics(v)
    return out


def test_query_export_has_paths_and_d_phi(project: Path, tmp_path: Path) -> None:
    out = tmp_path / "q.mcap"
    assert export(project, out, "--dataset", "query_1") == 0
    _, channels, msgs, raw = read_mcap(out)
    assert channels["/query_path"] == ("nav_msgs/msg/Path", "ros2msg", "cdr")
    reloc = pd.read_csv(project / "outputs" / "query_1" / "relocalization.csv")
    t_ns = (reloc["stamp_sec"] * 10**9 + reloc["stamp_nanosec"]).tolist()
    for topic, col in (
        ("/relocalization/distance_m", "distance_m"),
        ("/relocalization/heading_error_deg", "heading_error_deg"),
    ):
        assert channels[topic] == ("std_msgs/msg/Float64", "ros2msg", "cdr")
        assert [t for t, _ in raw[topic]] == t_ns
        np.testing.assert_allclose([m.data for m in msgs[topic]], reloc[col], rtol=0, atol=1e-12)
    aligned = artifact(project, "align", "query_1", "trajectory")
    (qpath,) = msgs["/query_path"]
    np.testing.assert_allclose(
        [[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in qpath.poses],
        aligned[["x_m", "y_m", "z_m"]],
        atol=1e-12,
    )
    assert len(msgs["/tf"]) == len(aligned)
    ref = read_trajectory(project / "outputs" / "reference")
    assert len(msgs["/reference_path"][0].poses) == len(ref)
    assert Counter(len(v) for t, v in msgs.items() if t in STATIC) == {1: 3}


def test_image_bag_copies_images(tmp_path: Path) -> None:
    simulate("room", tmp_path / "bags", frames=12, query_frames=3, detections=False)
    (tmp_path / "pipeline.yaml").write_text(
        "datasets:\n  reference: {source: bags/reference}\nstages:\n  pnp: {tag_size: 0.16}\n"
    )
    assert tagtrail.cli.main(["run", "-p", str(tmp_path / "pipeline.yaml")]) == 0
    out = tmp_path / "run.mcap"
    assert export(tmp_path, out) == 0
    _, channels, msgs, raw = read_mcap(out)
    src = source_messages(tmp_path / "bags" / "reference")
    assert channels["/camera/color/image_raw"] == ("sensor_msgs/msg/Image", "ros2msg", "cdr")
    assert [b for _, b in raw["/camera/color/image_raw"]] == src["/camera/color/image_raw"]
    img = msgs["/camera/color/image_raw"][0]
    assert (img.width, img.height, img.header.frame_id) == (640, 480, "camera_color_optical_frame")
    layout = (tmp_path / "run.layout.json").read_text()
    assert '"imageTopic": "/camera/color/image_raw"' in layout
    assert '"calibrationTopic": "/camera/color/camera_info"' in layout
    assert "{image_topic}" not in layout

    out2 = tmp_path / "light.mcap"
    assert export(tmp_path, out2, "--no-images") == 0
    _, channels2, _, _ = read_mcap(out2)
    assert "/camera/color/image_raw" not in channels2 and "/detections/annotations" in channels2


def test_errors_are_one_line_and_leave_nothing(
    project: Path, tmp_path: Path, capsys: Capsys
) -> None:
    capsys.readouterr()
    assert export(project, tmp_path / "x.mcap", "--dataset", "qurey_1") == 2
    assert "unknown dataset 'qurey_1'" in one_error_line(capsys)
    assert export(project, tmp_path, "--dataset", "query_1") == 2
    assert "is a folder" in one_error_line(capsys)
    # a changed parameter: the artifacts are not this run's; nothing is written
    assert export(project, tmp_path / "x.mcap", "-S", "optimize.f_scale=0.07") == 2
    line = one_error_line(capsys)
    assert "is not up to date: run `tagtrail run -p" in line and "-S optimize.f_scale=0.07" in line
    # a source gone since the run: one line, no MCAP and no temporary file left
    moved = project / "bags" / "query_1_moved"
    shutil.move(project / "bags" / "query_1", moved)
    try:
        assert export(project, tmp_path / "q.mcap", "--dataset", "query_1") == 2
        assert "query_1" in one_error_line(capsys)
    finally:
        shutil.move(moved, project / "bags" / "query_1")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_image_folder_as_compressed_images(tmp_path: Path) -> None:
    """An image folder (PNGs of a simulated bag, its camera_info as camera.yaml, stamps.csv):
    the files themselves as CompressedImage, the camera as CameraInfo at each image's stamp."""
    import cv2
    import yaml

    simulate("room", tmp_path / "bags", frames=8, query_frames=3, detections=False)
    folder = tmp_path / "images"
    folder.mkdir()
    reader = open_bag(tmp_path / "bags" / "reference")
    stamps, info = [], None
    try:
        for conn, _, data in reader.messages():
            if conn.msgtype not in ("sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/Image"):
                continue  # /odom, /tf_static
            msg = reader.deserialize(data, conn.msgtype)
            t_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            if conn.msgtype == "sensor_msgs/msg/CameraInfo":
                info = msg
            elif conn.msgtype == "sensor_msgs/msg/Image":
                img = np.asarray(msg.data, np.uint8).reshape(msg.height, msg.width, -1)
                name = f"frame_{len(stamps):03d}.png"
                cv2.imwrite(
                    str(folder / name),
                    cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.shape[2] == 3 else img,
                )
                stamps.append((name, t_ns))
    finally:
        reader.close()
    assert info is not None and len(stamps) == 8
    (folder / "stamps.csv").write_text(
        "file,stamp_sec,stamp_nanosec\n"
        + "".join(f"{n},{t // 10**9},{t % 10**9}\n" for n, t in stamps)
    )
    mat = {"rows": 3, "cols": 3, "data": [float(v) for v in info.k]}
    (folder / "camera.yaml").write_text(
        yaml.safe_dump(
            {
                "image_width": int(info.width),
                "image_height": int(info.height),
                "camera_matrix": mat,
                "distortion_model": str(info.distortion_model),
                "distortion_coefficients": {
                    "rows": 1,
                    "cols": len(info.d),
                    "data": [float(v) for v in info.d],
                },
            }
        )
    )
    (tmp_path / "pipeline.yaml").write_text(
        "datasets:\n  reference: {source: images}\nstages:\n  pnp: {tag_size: 0.16}\n"
    )
    assert tagtrail.cli.main(["run", "-p", str(tmp_path / "pipeline.yaml")]) == 0
    out = tmp_path / "folder.mcap"
    assert export(tmp_path, out) == 0
    _, channels, msgs, raw = read_mcap(out)
    assert channels["/camera/image/compressed"] == (
        "sensor_msgs/msg/CompressedImage",
        "ros2msg",
        "cdr",
    )
    imgs = msgs["/camera/image/compressed"]
    assert [m.format for m in imgs] == ["png"] * 8
    assert [bytes(m.data) for m in imgs] == [(folder / n).read_bytes() for n, _ in stamps]
    assert [t for t, _ in raw["/camera/image/compressed"]] == [t for _, t in stamps]
    cams = msgs["/camera/camera_info"]
    assert [t for t, _ in raw["/camera/camera_info"]] == [t for _, t in stamps]
    np.testing.assert_allclose(cams[0].k, info.k, rtol=0, atol=0)
    assert (cams[0].width, cams[0].height, cams[0].header.frame_id) == (640, 480, "camera")
    assert {m.transforms[0].child_frame_id for m in msgs["/tf"]} == {"camera"}
    layout = (tmp_path / "folder.layout.json").read_text()
    assert '"imageTopic": "/camera/image/compressed"' in layout

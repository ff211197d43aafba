"""The live node's core (no zenoh): equal to the report stage, alignment files, bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tagtrail.errors import SourceError
from tagtrail.geometry import se3
from tagtrail.geometry.association import TrackParams
from tagtrail.geometry.reference_path import reference_plane
from tagtrail.geometry.registration import Alignment, world_transform
from tagtrail.schemas.artifacts import poses
from tagtrail.stages import report as report_stage
from tagtrail.stages.align import transform_trajectory
from tagtrail.stream import codec
from tagtrail.stream.reloc_node import OUTPUTS, Relocalizer, load_alignment
from tagtrail.stream.stats import DropError, Stats
from tests.stream.cases import frame, planar_poses, query_frame, reference_frame

BLOCK = {
    "model": "similarity",
    "scale": 0.98,
    "rotation_deg": -20.0,
    "translation": [0.3, 0.1],
    "inliers": 3,
    "common_tags": 3,
    "rms_m": 0.002,
}


def _payloads(query) -> list[bytes]:
    enc = codec.PoseStampedEncoder("map")
    sec, nsec = np.divmod(query["t_ns"].to_numpy(), 10**9)
    vals = query[["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]].to_numpy().tolist()
    return [enc(int(s), int(n), *v) for s, n, v in zip(sec, nsec, vals, strict=True)]


@pytest.mark.parametrize(("n_ref", "plane"), [(400, "xz"), (20_000, "auto")])
def test_process_equals_report_stage(tmp_path: Path, n_ref: int, plane: str) -> None:
    """Brute-force (small) and k-d tree (large reference) paths of ``query_one``."""
    ref, query = reference_frame(n_ref), query_frame(300, seed=1)
    (tmp_path / "a.json").write_text(json.dumps({"plane": plane, "alignment": BLOCK}))
    A, R, file_plane = load_alignment(tmp_path / "a.json", ref)
    assert file_plane == plane
    node = Relocalizer(ref, plane, (A, R), path_max_points=500)
    a = math.radians(BLOCK["rotation_deg"])
    al = Alignment(
        "similarity",
        BLOCK["scale"],
        np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]),
        np.array(BLOCK["translation"]),
        np.ones(3, bool),
        0.0,
    )
    A2, R2 = world_transform(al, reference_plane(plane, *poses(ref)))
    off = report_stage.run(
        transform_trajectory(query, A2, R2),
        ref,
        BLOCK,
        report_stage.Params(mode="trajectory", plane=plane),
    )["relocalization"]
    stats = Stats("t")
    outs = [node.process(codec.decode_pose(p)) for p in _payloads(query)]
    np.testing.assert_allclose([o.distance_m for o in outs], off["distance_m"], atol=1e-9, rtol=0)
    np.testing.assert_allclose(
        [o.heading_error_deg for o in outs], off["heading_error_deg"], atol=1e-9, rtol=0
    )
    np.testing.assert_allclose([o.u for o in outs], off["query_u"], atol=1e-9)
    np.testing.assert_allclose([o.ref_v for o in outs], off["ref_v"], atol=1e-9)
    keyed = node.handle(_payloads(query)[0], stats)
    assert [k for k, _ in keyed] == [f"relocalization/{k}" for k in OUTPUTS]
    path = codec.deserialize(node.path_cdr, codec.PATH)
    assert len(path.poses) == min(n_ref, 500)


def test_drive_along_long_reference_equals_batch_query() -> None:
    """Consecutive poses (the long-path index starts from its previous answer) drifting ±0.3 m
    to both sides of a 200,000-sample loop, the concave side included: k* and D of each pose
    equal the batch k-d tree query over every sample."""
    ref = reference_frame(200_000)
    node = Relocalizer(ref, "xz", track=TrackParams(association="nearest"))  # Eq. 3.12
    s = np.linspace(0.0, 4 * np.pi, 1500)  # two laps
    off = 0.3 * np.sin(np.linspace(0.0, 14 * np.pi, len(s)))
    tu, tv = -1.5 * np.sin(s), np.cos(s)
    nu, nv = tv / np.hypot(tu, tv), -tu / np.hypot(tu, tv)
    T = planar_poses(
        1.5 * np.cos(s) + off * nu,
        np.sin(s) + off * nv,
        np.arctan2(tv, tu) + 0.3,
        np.full(len(s), -0.13),
    )
    query = frame(T, np.arange(len(s), dtype=np.int64))
    outs = [node.process(codec.decode_pose(p)) for p in _payloads(query)]
    want = node.path.query(T[:, :3, 3], T[:, :3, :3])
    assert [o.nearest_ref_idx for o in outs] == want.ref_idx.tolist()
    np.testing.assert_allclose([o.distance_m for o in outs], want.distance_m, atol=1e-12, rtol=0)
    np.testing.assert_allclose(
        [o.heading_error_rad for o in outs], want.phi_rad, atol=1e-12, rtol=0
    )


def test_alignment_files(tmp_path: Path) -> None:
    ref = reference_frame(100)
    A0 = np.eye(4)
    A0[:3, :3] = 1.01 * se3.R_from_rotvec([0.1, 0.2, 0.3])
    A0[:3, 3] = [1, 2, 3]
    docs = {
        "none.json": {"model": "none", "scale": 1.0},
        "block.json": BLOCK,
        "matrix.json": {"model": "sim3", "ref_A_query": A0.tolist()},
    }
    for name, doc in docs.items():
        (tmp_path / name).write_text(json.dumps(doc))
    A, R, _ = load_alignment(tmp_path / "none.json", ref)
    assert np.array_equal(A, np.eye(4)) and np.array_equal(R, np.eye(3))
    A, R, plane = load_alignment(tmp_path / "block.json", ref, "xz")
    assert plane is None and np.isclose(A[1, 1], 1.0) and np.isclose(np.linalg.det(R), 1.0)
    A, R, _ = load_alignment(tmp_path / "matrix.json", ref)
    np.testing.assert_allclose(A, A0)
    np.testing.assert_allclose(R, se3.R_from_rotvec([0.1, 0.2, 0.3]), atol=1e-12)
    bad = {
        "sim3.json": {"model": "sim3", "scale": 1.0, "rotation_deg": 3.0},
        "garbage.json": "[1, 2",
        "plane.json": {"plane": "zz", "alignment": BLOCK},
        "empty.json": {},
    }
    for name, doc in bad.items():
        (tmp_path / name).write_text(doc if isinstance(doc, str) else json.dumps(doc))
        with pytest.raises(SourceError, match=name):
            load_alignment(tmp_path / name, ref)


def test_bad_input_raises_drop_with_reason() -> None:
    node = Relocalizer(reference_frame(50), "xz")
    enc = codec.PoseStampedEncoder("map")
    cases = {
        "malformed": [b"", b"\x00\x01\x00\x00", codec.encode_float64(2.0)],
        "non_finite": [
            enc(1, 0, math.nan, 0, 0, 0, 0, 0, 1),
            enc(1, 0, 0, 0, 0, 0, math.inf, 0, 1),
        ],
        "bad_quaternion": [enc(1, 0, 0, 0, 0, 0, 0, 0, 0)],
    }
    for reason, payloads in cases.items():
        for p in payloads:
            with pytest.raises(DropError) as info:
                node.handle(p)
            assert info.value.reason == reason
    # an unnormalised quaternion is normalised (as the offline reader's scipy does)
    a = node.process(codec.decode_pose(enc(1, 0, 1.0, 0, 0.5, 0, 0.6, 0, 0.8)))
    b = node.process(codec.decode_pose(enc(1, 0, 1.0, 0, 0.5, 0, 3.0, 0, 4.0)))
    assert a.heading_error_rad == pytest.approx(b.heading_error_rad, abs=1e-12)

"""``simulate()``: build a scenario's scenes, write each recording and its ground truth, atomically.

``OUT/<recording>/`` is a rosbag2 folder (or an observations folder), ``OUT/<recording>/
ground_truth/`` holds ``trajectory.csv`` (world_T_cam per frame), ``tag_map.yaml``/``.csv``
(world_T_tag, with ``size_m``; ``n_obs`` = frames in which the tag is detectable), ``scene.yaml``
and, for parked recordings, ``test_poses.csv``; with odometry, ``odometry_truth.csv`` (world_T_base
at each ``/odom`` message's measurement time) and, in ``scene.yaml``, ``base_T_camera`` and the
odometry's drawn errors. World = the anchor tag's frame. Everything is
written into a hidden temporary folder of ``OUT`` and renamed into place at the end.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from tagtrail.errors import SpecError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.se3 import compose, xyz_quat_from_T
from tagtrail.io.layouts import atomic_write_text, write_tag_map, write_trajectory_csv
from tagtrail.schemas.artifacts import POSE_COLS
from tagtrail.sim import bagwrite, odometry
from tagtrail.sim.camera import FRAME_ID, tag_visibility
from tagtrail.sim.odometry import OdomSample, WheelOdometry
from tagtrail.sim.scenarios import RECORDINGS, SCENARIOS, SimOptions, build
from tagtrail.sim.scene import Scene


def make_options(**options: Any) -> SimOptions:
    """``SimOptions`` from keyword arguments, with a did-you-mean error for unknown names."""
    names = [f.name for f in dataclasses.fields(SimOptions)]
    for key in options:
        if key not in names:
            hint = difflib.get_close_matches(key, names, n=1)
            extra = f" (did you mean {hint[0]!r}?)" if hint else ""
            raise SpecError(f"unknown simulate option {key!r}{extra}")
    return SimOptions(**options)


def _pose_frame(T: F64, t_ns: np.ndarray) -> pd.DataFrame:
    xyz, q = xyz_quat_from_T(T)
    df = pd.DataFrame(np.hstack([xyz, q]), columns=POSE_COLS)
    df.insert(0, "t_ns", np.asarray(t_ns, dtype=np.int64))
    return df


ODOM_STREAM = 1  # the odometry's generator: default_rng([seed, recording, ODOM_STREAM])
ODOM_TRUTH_COLS = ["t_ns", "meas_t_ns", *POSE_COLS]


def _xyzq(T: F64) -> list[float]:
    xyz, q = xyz_quat_from_T(T)
    return [float(v) for v in (*xyz, *q)]


def _odometry_doc(
    folder: Path, scene: Scene, opts: SimOptions, odo: WheelOdometry, samples: list[OdomSample]
) -> dict[str, Any]:
    """Write ``odometry_truth.csv`` (t_ns = the header stamp, meas_t_ns = the time the state
    was measured, world_T_base then); returns scene.yaml's ``odometry`` block."""
    world_T_base = compose(scene.world_T_scene[None], np.stack([s.scene_T_base for s in samples]))
    df = _pose_frame(world_T_base, np.array([s.stamp_ns for s in samples]))
    df.insert(1, "meas_t_ns", np.array([s.meas_ns for s in samples], dtype=np.int64))
    atomic_write_text(folder / "odometry_truth.csv", df.to_csv(index=False, float_format="%.17g"))
    lat = np.array([s.stamp_ns - s.meas_ns for s in samples]) / 1e6
    slip = opts.slip()
    return {
        "topic": odometry.ODOM_TOPIC,
        "frame_id": odometry.ODOM_FRAME,
        "child_frame_id": odometry.BASE_FRAME,
        "rate_hz": odometry.RATE_HZ,
        "messages": len(samples),
        "latency_ms": {"min": float(lat.min()), "max": float(lat.max()), "range": [2.0, 8.0]},
        "scale_left": odo.scale_l,
        "scale_right": odo.scale_r,
        "drift_dps": float(np.degrees(odo.drift_rps)),
        "slip_per_mps2": odo.slip_per_mps2,
        "slip": None if slip is None else dataclasses.asdict(slip),
        "world_T_odom": _xyzq(world_T_base[0]),
        "truth": "odometry_truth.csv",
    }


def write_ground_truth(
    folder: Path,
    scene: Scene,
    scenario: str,
    opts: SimOptions,
    odom: tuple[WheelOdometry, list[OdomSample]] | None = None,
) -> None:
    """Write the ground-truth files of ``scene`` into ``folder`` (world = anchor tag frame);
    ``odom``: the recorded odometry (its model and samples), for its truth."""
    folder.mkdir(parents=True, exist_ok=True)
    world_T_cam = scene.world_T_cam()
    write_trajectory_csv(folder / "trajectory.csv", _pose_frame(world_T_cam, scene.t_ns))
    if scene.parked:
        write_trajectory_csv(
            folder / "test_poses.csv", _pose_frame(world_T_cam[:1], scene.t_ns[:1])
        )
    vis = tag_visibility(
        scene.camera,
        scene.cam_T_tags(),
        scene.tag_sizes,
        max_range_m=opts.max_range_m,
        max_incidence_deg=opts.max_incidence_deg,
    )
    tags = _pose_frame(scene.world_T_tags(), np.zeros(len(scene.tags)))
    tags = tags.drop(columns="t_ns")
    tags.insert(0, "tag_id", scene.tag_ids)
    tags["n_obs"] = vis.visible.sum(axis=0).astype(np.int64)
    tags["size_m"] = scene.tag_sizes
    write_tag_map(folder, tags, scene.anchor_id)
    doc = {
        "scenario": scenario,
        "recording": scene.name,
        "world_frame": f"anchor tag frame (tag36h11:{scene.anchor_id}); floor = its x-z plane",
        "anchor_id": scene.anchor_id,
        "seed": opts.seed,
        "camera": {**scene.camera.to_dict(), "frame_id": FRAME_ID},
        "tags": [{"id": int(t.tag_id), "size_m": float(t.size_m)} for t in scene.tags],
        "tag_family": "tag36h11",
        "n_frames": len(scene.t_ns),
        "fps": opts.fps,
        "parked": scene.parked,
        "content": (
            "observations"
            if scenario == "observations"
            else "detections"
            if opts.detections
            else "compressed images"
            if opts.compressed
            else "images"
        ),
        "options": opts.to_dict(),
        "info": scene.info,
    }
    if odom is not None:
        doc["base_T_camera"] = _xyzq(odometry.base_T_cam(opts.mount))
        doc["base_T_camera_frames"] = [odometry.BASE_FRAME, FRAME_ID]
        doc["odometry"] = _odometry_doc(folder, scene, opts, *odom)
    atomic_write_text(folder / "scene.yaml", yaml.safe_dump(_plain(doc), sort_keys=False))


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


def simulate(scenario: str, out: Path, **options: Any) -> dict[str, Path]:
    """Simulate ``scenario`` into ``out``; returns {recording name: its folder}.

    ``options`` are :class:`SimOptions` fields (e.g. ``frames=60``, ``detections=True``,
    ``seed=3``, ``force=True``). Refuses to overwrite an existing recording unless ``force``.
    """
    if scenario not in SCENARIOS:
        raise SpecError(f"unknown scenario {scenario!r}; choose one of {', '.join(SCENARIOS)}")
    opts = make_options(**options)
    if scenario == "observations" and opts.odom:
        raise SpecError("--odom: the observations scenario writes no bag (use --no-odom)")
    out = Path(out)
    existing = [out / n for n in RECORDINGS[scenario] if os.path.lexists(out / n)]
    if existing and not opts.force:
        raise SpecError(f"{existing[0]} exists already; use --force to overwrite it")
    scenes = build(scenario, opts)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".simulate-{scenario}-", dir=out))
    try:
        for k, scene in enumerate(scenes):
            rng = np.random.default_rng([opts.seed, k])
            folder = tmp / scene.name
            odom = None
            if scenario == "observations":
                bagwrite.write_observations(folder, scene, opts, rng)
            else:
                if opts.odom is not False:
                    odom = odometry.odometry_stream(
                        scene.scene_T_cam,
                        scene.t_ns,
                        opts.mount,
                        np.random.default_rng([opts.seed, k, ODOM_STREAM]),
                        opts.odom_scale_error,
                        opts.slip(),
                    )
                bagwrite.write_bag(folder, scene, opts, rng, odom[1] if odom else None)
            write_ground_truth(folder / "ground_truth", scene, scenario, opts, odom)
        result = {}
        for scene in scenes:
            dest = out / scene.name
            if dest.is_symlink() or dest.is_file():  # a link itself, never what it leads to
                dest.unlink()
            elif dest.exists():
                shutil.rmtree(dest)
            os.replace(tmp / scene.name, dest)
            result[scene.name] = dest
        return result
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

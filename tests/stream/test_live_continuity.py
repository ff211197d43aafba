"""Live localization with continuity (``stream localize --smooth``): the fixed-lag smoother with
the offline joint model's priors, dead reckoning on wheel odometry between fixes and through a
blackout, PoseWithCovarianceStamped and the age of the last fix. Checked against the
simulator's ground truth (which the code under test did not produce)."""

from __future__ import annotations

import json
import math
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from tagtrail.geometry.joint import (
    CornerRows,
    JointSettings,
    corner_problem,
    solve_on_corners,
)
from tagtrail.io.layouts import read_tag_map, read_trajectory
from tagtrail.sim import limo
from tagtrail.sim.follow import eight_scene
from tagtrail.sim.scenarios import SimOptions
from tagtrail.sim.simulate import simulate
from tagtrail.stream import codec, localize
from tagtrail.stream.continuity import DeadReckoning, LivePoses, Smoother, SmootherSettings
from tagtrail.stream.localize import Localizer
from tagtrail.stream.replay import bag_messages
from tagtrail.stream.session import wait_matching
from tagtrail.stream.stats import DropError
from tests.stream.helpers import Collector, free_port, loopback, running

N_FRAMES = 300


@pytest.fixture(scope="module")
def noisy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate(
        "circle",
        tmp_path_factory.mktemp("cont"),
        frames=N_FRAMES,
        detections=True,
        corner_noise_px=0.3,
        seed=5,
    )["circle"]


def _live(loc: Localizer, settings: SmootherSettings | None = None, **kw: float) -> LivePoses:
    return LivePoses(
        Smoother(loc.world_T_tag, loc.size_m, settings or SmootherSettings()),
        DeadReckoning(**kw),
        "tag_only_pose",
        "localize",
        "map",
    )


def _err(payload: bytes, gt: object) -> float:
    q = codec.decode_pose(payload)
    row = gt.loc[q.sec * 10**9 + q.nanosec]  # type: ignore[attr-defined]
    return float(np.linalg.norm([q.x - row.x_m, q.y - row.y_m, q.z - row.z_m]))


def _pose7(payload: bytes) -> tuple[float, ...]:
    q = codec.decode_pose(payload)
    return (q.x, q.y, q.z, q.qx, q.qy, q.qz, q.qw)


def _offline(loc: Localizer, obs: list[tuple[Any, ...]]) -> tuple[Any, Any]:
    """The offline joint solve (its problem and solution) of the frames ``obs`` — ``(t_ns,
    map rows, corners px)`` as the node took them — the map held fixed."""
    from tagtrail.geometry.ippe import solve_ippe

    frame_idx = np.concatenate([[i] * len(o[1]) for i, o in enumerate(obs)])
    t_all = np.concatenate([[o[0]] * len(o[1]) for o in obs])
    tag = np.concatenate([o[1] for o in obs])
    px = np.concatenate([o[2] for o in obs]).reshape(-1, 4, 2)
    assert loc.camera is not None
    ippe, _ = solve_ippe(px, loc.size_m[tag], loc.camera)
    st = JointSettings()
    rows = CornerRows(frame_idx, t_all, loc.ids[tag], px, loc.size_m[tag], ippe)
    pb = corner_problem(rows, tag, loc.camera, st, True)
    return pb, solve_on_corners(pb, loc.world_T_tag, np.zeros(len(loc.ids), bool), st)


def test_smoothed_poses_beat_per_frame_and_approach_offline(noisy: Path) -> None:
    """Every frame posed; the smoothed poses' error is below the per-frame poses' and within
    2.5x the offline joint solve's on the same frames (measured: 2.2 mm vs 5.0 mm per frame vs
    1.2 mm offline, bench/LIVE_POSE.md; with 0.3 px corner noise the issue's 1.2x is met only
    on the rendered recording)."""
    gt = read_trajectory(noisy / "ground_truth" / "trajectory.csv").set_index("t_ns")
    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections"])
    loc = Localizer(tags)
    live = _live(loc)
    e_frame, e_live, obs = [], [], []
    info = m.payloads[m.keys.index("camera_info")]
    loc.on_camera_info(info)
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k != "detections":
            continue
        loc.live = None
        single = loc.on_detections(p)
        assert loc._last_obs is not None
        q = codec.decode_pose(single[0][1])
        obs.append((q.sec * 10**9 + q.nanosec, *loc._last_obs))
        loc.smooth(live)
        out = dict(loc.on_detections(p))
        assert set(out) == set(live.keys())
        cov = codec.deserialize(
            out["localize/pose_with_covariance"], codec.POSE_TYPES["pose_with_covariance"]
        )
        c = np.asarray(cov.pose.covariance).reshape(6, 6)
        assert np.all(np.linalg.eigvalsh(0.5 * (c + c.T)) > 0)  # a covariance, no placeholder
        state = json.loads(out["localize/state"])
        assert state["source"] == "tags" and state["fix_age_s"] == 0.0
        assert struct_f64(out["localize/fix_age_s"]) == 0.0
        e_frame.append(_err(single[0][1], gt))
        e_live.append(_err(out["tag_only_pose"], gt))
    assert len(e_live) == N_FRAMES
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in (("f", e_frame), ("l", e_live))}
    pb, sol = _offline(loc, obs)  # the offline joint solve on the same corners
    c_off = -np.einsum("fji,fj->fi", sol.res.R_cam, sol.res.t_cam)
    g = gt.loc[pb.t_ns][["x_m", "y_m", "z_m"]].to_numpy()
    rms_off = float(np.sqrt(np.mean(np.sum((c_off - g) ** 2, axis=1))))
    assert rms["l"] < 0.8 * rms["f"], rms
    assert rms["l"] < 2.5 * rms_off, (rms, rms_off)
    assert live.smoother.mount is not None  # a wheeled robot: the drive prior holds it


def struct_f64(payload: bytes) -> float:
    return float(np.frombuffer(payload[4:12], "<f8")[0])


def test_dead_reckoning_is_exact_on_true_odometry() -> None:
    """The LIMO's camera (0.084 m ahead of the base) on a curve: the fix carried 0.5 s forward
    by error-free odometry lands on the true pose (both the lever arm and the turn)."""
    opts = SimOptions()
    scene = eight_scene(opts)
    W = scene.world_T_scene
    x = y = yaw = 0.0
    poses, odo = [], []
    for i in range(60):
        poses.append(W @ limo.camera_pose(scene, x, y, yaw))
        odo.append((i * 10_000_000, x, y, yaw))
        x += 0.3 * math.cos(yaw) * 0.01
        y += 0.3 * math.sin(yaw) * 0.01
        yaw += 1.0 * 0.01
    up = -poses[0][:3, 1]  # the camera's y points down
    for lever, exact in ((opts.mount.forward_m, True), (0.0, False)):
        d = DeadReckoning(latency_s=0.0, camera_forward_m=lever)
        for o in odo:
            d.add_odometry(*o)
        d.fix, d.up = (odo[5][0], poses[5]), up
        T = d.pose(odo[55][0])
        assert T is not None
        err = float(np.linalg.norm(T[:3, 3] - poses[55][:3, 3]))
        assert (err < 1e-9) if exact else (err > 0.01), err
    d.fix = (odo[5][0], poses[5])
    assert d.pose(odo[55][0] + 10**9) is None  # beyond the odometry: nothing invented
    d.max_age_s = 0.2
    assert d.pose(odo[55][0]) is None  # the fix too old


def test_dead_reckoning_takes_the_odometrys_errors_off() -> None:
    """Wheels that read 2 % long, 0.2 rad of yaw per metre (two wheels 3.5 % apart) and 0.005
    rad/s of drift, carried 2 s round an arc at 0.3 m/s, 1 rad/s: taken as they are the pose
    lands 4 cm off; with the errors the smoother read (``errors``), on it (the same model);
    pose after pose, message by message, as through a blackout."""
    opts = SimOptions()
    scene = eight_scene(opts)
    W = scene.world_T_scene
    x = y = yaw = 0.0  # the truth
    ox = oy = oyaw = 0.0  # what the wheels read
    poses, odo = [], []
    for i in range(201):
        poses.append(W @ limo.camera_pose(scene, x, y, yaw))
        odo.append((i * 10_000_000, ox, oy, oyaw))
        v, w, h = 0.3, 1.0, 0.01
        ox += 1.02 * v * h * math.cos(oyaw)
        oy += 1.02 * v * h * math.sin(oyaw)
        oyaw += w * h + 0.2 * 1.02 * v * h + 0.005 * h
        x += v * h * math.cos(yaw)
        y += v * h * math.sin(yaw)
        yaw += w * h
    up = -poses[0][:3, 1]
    errs = {}
    for name, errors in (("raw", (1.0, 1.0, 0.0, 0.0)), ("read", (1.02, 1.0, 0.2, 0.005))):
        d = DeadReckoning(latency_s=0.0, camera_forward_m=opts.mount.forward_m, errors=errors)
        d.fix, d.up = (0, poses[0]), up
        worst = 0.0
        for i, o in enumerate(odo):
            d.add_odometry(*o)
            if i:
                T = d.pose(o[0])
                assert T is not None
                worst = max(worst, float(np.linalg.norm(T[:3, 3] - poses[i][:3, 3])))
        errs[name] = worst
    assert errs["raw"] > 0.03 and errs["read"] < 1e-9, errs


def test_odometry_stamps_are_publication_times() -> None:
    d = DeadReckoning(latency_s=0.005)
    assert d.add_odometry(1_000_000_000, 0.0, 0.0, 0.0) == 995_000_000
    assert d.add_odometry(990_000_000, 1.0, 0.0, 0.0) == 985_000_000  # older: not kept
    assert len(d.odo) == 1


@pytest.mark.slow
def test_node_publishes_per_frame_and_between_frames_with_odometry(tmp_path: Path) -> None:
    """A real ``stream localize --smooth --odom-key odom`` process: the LIMO's detections at
    30 Hz and odometry at 50 Hz over zenoh; a pose per frame and per odometry message after
    the first fix, in time order, PoseWithCovarianceStamped beside PoseStamped; through 1 s
    without tags the odometry carries the pose (fix age grows to ~1 s, error < 5 cm)."""
    opts = SimOptions(speed_mps=0.3, detections=True, seed=0)
    scene = eight_scene(opts)
    from tagtrail.sim.simulate import write_ground_truth

    gt = tmp_path / "gt"
    write_ground_truth(gt, scene, "follow", opts)
    rng = np.random.default_rng(0)
    odo = limo.WheelOdometry(rng)
    port = free_port()
    args = [
        "localize",
        "--map",
        str(gt),
        "--tag-size",
        str(opts.tag_size_m),
        "--smooth",
        "--odom-key",
        "odom",
        "--camera-forward",
        str(opts.mount.forward_m),
        "--listen",
        loopback(port),
        "--duration",
        "60",
        "--stats-period",
        "0",
    ]
    keys = ["tag_only_pose", "localize/pose_with_covariance", "localize/state"]
    truth: dict[int, np.ndarray] = {}
    n_frames, n_odo = 90, 150  # 3 s; tags hidden from 1.5 s to 2.5 s
    with running(args) as (node,):
        node.wait_for("localize: ready")
        sub = Collector(port, keys)
        pubs = {
            k: sub.session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
            for k in ("detections", "camera_info", "odom")
        }
        try:
            for p in pubs.values():
                assert wait_matching(p, 15, threading.Event())
            t0 = 1_700_000_000_000_000_000
            x = y = 0.0
            yaw = 0.5
            base = scene.scene_T_cam[0]
            fwd = opts.mount.forward_m
            y0 = math.atan2(base[1, 2], base[0, 2])
            x, y, yaw = base[0, 3] - fwd * math.cos(y0), base[1, 3] - fwd * math.sin(y0), y0
            dt = 0.002
            for i in range(1500):  # 3 s in 2 ms steps
                t = i * dt
                stamp = t0 + int(round(t * 1e9))
                T = limo.camera_pose(scene, x, y, yaw)
                truth[stamp] = scene.world_T_scene @ T
                if i % 16 == 0 and i // 16 < n_frames:  # ~31 Hz frames
                    blind = 1.5 <= t < 2.5
                    det, info, _ = limo.detections(scene, T, stamp, opts, rng, blind)
                    pubs["camera_info"].put(info)
                    pubs["detections"].put(det)
                if i % 10 == 0 and i // 10 < n_odo:  # 50 Hz odometry, stamped 5 ms later
                    pubs["odom"].put(odo.message(stamp + 5_000_000))
                v, w = 0.3, 0.4
                odo.step(v, w, dt)
                x += v * math.cos(yaw + 0.5 * w * dt) * dt
                y += v * math.sin(yaw + 0.5 * w * dt) * dt
                yaw += w * dt
            sub.wait_until("localize/state", lambda v: len(v) >= 150, timeout=40)
            time.sleep(1.0)  # the rest of the flood
            got = sub.wait("localize/state", 150)
            helpers = _children(node.p.pid, "tagtrail.stream.continuity:_resolve")
        finally:
            for p in pubs.values():
                p.undeclare()
            sub.close()
        assert node.stop(sig=signal.SIGINT) == 0, node.output
    assert "without --camera-forward" not in node.output
    # the window's re-solve ran in its background process, which left with the node
    if sys.platform == "linux":
        assert len(helpers) == 1, helpers
        deadline = time.monotonic() + 5.0
        while Path(f"/proc/{helpers[0]}").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not Path(f"/proc/{helpers[0]}").exists()
    states = [json.loads(s) for s in got]
    stamps = [s["stamp_sec"] * 10**9 + s["stamp_nanosec"] for s in states]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    src = [s["source"] for s in states]
    print({k: src.count(k) for k in ("tags", "odometry")}, len(states))
    assert src.count("tags") >= 30 and src.count("odometry") >= 100
    ages = np.array([s["fix_age_s"] for s in states])
    assert 0.9 < ages.max() < 1.2  # the blackout, bridged
    poses = sub.samples["tag_only_pose"]
    covs = sub.samples["localize/pose_with_covariance"]
    assert len(poses) == len(covs) >= len(states)
    keys_t = np.array(sorted(truth))
    errs = []
    for raw in poses:
        q = codec.decode_pose(raw)
        s = q.sec * 10**9 + q.nanosec
        G = truth[int(keys_t[np.argmin(np.abs(keys_t - s))])]
        errs.append(float(np.linalg.norm([q.x - G[0, 3], q.y - G[1, 3], q.z - G[2, 3]])))
    assert max(errs) < 0.05, max(errs)


def _children(pid: int, needle: str) -> list[int]:
    """Child processes of ``pid`` whose command line holds ``needle`` (Linux's /proc)."""
    out = []
    for d in Path("/proc").glob("[0-9]*"):
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid and needle in cmd:
            out.append(int(d.name))
    return out


def test_smoothing_without_the_mount_says_so(noisy: Path) -> None:
    """``--smooth`` with neither ``--camera-forward`` nor a profile that gives it: one warning
    line naming the flag (the lever arm is 0 until the robot has turned enough to fit it)."""
    args = ["localize", "--map", str(noisy / "ground_truth" / "tag_map.yaml"), "--smooth"]
    args += ["--listen", loopback(free_port()), "--duration", "30", "--stats-period", "0"]
    with running(args) as (node,):
        node.wait_for("localize: ready")
        assert node.stop() == 0, node.output
    lines = [ln for ln in node.output.splitlines() if "without --camera-forward" in ln]
    assert len(lines) == 1, node.output


def test_further_priors_join_each_window(noisy: Path) -> None:
    """The seam for the odometry prior: each window's solve asks every ``extra`` factory for a
    prior on its frames' stamps (here the last 1 s, at most 30 frames), and takes what it gives."""
    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections"])
    loc = Localizer(tags)
    seen: list[tuple[np.ndarray, list[int]]] = []

    def pinned(t_s: np.ndarray, t_ns: list[int]) -> object:
        seen.append((t_s, t_ns))
        return None

    sm = Smoother(
        loc.world_T_tag,
        loc.size_m,
        SmootherSettings(window_s=1.0, max_frames=30, step_first=False),
        extra=[pinned],
    )
    loc.smooth(LivePoses(sm, DeadReckoning(), "tag_only_pose", "localize", "map"))
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    n = 0
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k == "detections" and n < 40:
            loc.on_detections(p)
            n += 1
    assert len(seen) == 40
    sizes = [len(t) for t, _ in seen]
    assert sizes[:3] == [1, 2, 3] and max(sizes) == 30
    for t_s, t_ns in seen:
        assert t_s[0] == 0.0 and np.allclose(t_s, (np.array(t_ns) - t_ns[0]) * 1e-9)
        assert t_s[-1] <= 1.0 + 1e-9


def test_a_slow_solve_shrinks_the_window(noisy: Path) -> None:
    """The time budget: solves that overrun it (the median of the last few) halve the window's
    frames (down to 5); fast ones let it grow back by one a frame, up to max_frames; a lone
    slow solve among fast ones (a hiccup of a loaded machine) leaves it alone."""
    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections"])
    loc = Localizer(tags)
    step = [0.05]  # s a solve takes on this clock
    now = [0.0]

    def clock() -> float:
        now[0] += step[0] / 2  # called before and after each solve
        return now[0]

    settings = SmootherSettings(window_s=1.0, max_frames=30, budget_ms=15.0)
    sm = Smoother(loc.world_T_tag, loc.size_m, settings, clock=clock)
    loc.smooth(LivePoses(sm, DeadReckoning(), "tag_only_pose", "localize", "map"))
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    dets = [p for k, p in zip(m.keys, m.payloads, strict=True) if k == "detections"]
    for p in dets[:10]:
        loc.on_detections(p)
    assert sm.n_max == 5 and len(sm.frames) <= 5
    step[0] = 0.001
    for p in dets[10:50]:
        loc.on_detections(p)
    assert sm.n_max == 30 and len(sm.frames) == 30
    for i, p in enumerate(dets[50:70]):
        step[0] = 0.2 if i % 5 == 0 else 0.001
        loc.on_detections(p)
        assert sm.n_max == 30


def _level_cameras(xy: np.ndarray, heading: np.ndarray, height: float = 0.2) -> np.ndarray:
    """cam_T_world ``(F, 4, 4)`` of a level camera (y down, z along ``heading`` in the xy
    plane, world z up) at ``xy``."""
    out = []
    for (x, y), h in zip(xy, heading, strict=True):
        z = np.array([np.cos(h), np.sin(h), 0.0])
        yy = np.array([0.0, 0.0, -1.0])
        R_wc = np.stack([np.cross(yy, z), yy, z], axis=1)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_wc.T, -R_wc.T @ np.array([x, y, height])
        out.append(T)
    return np.stack(out)


def test_the_live_plane_leaves_outlier_poses_out() -> None:
    """A level camera's history with 5 % of its poses metres off (a lone far tag's mirror
    pose): the plane fitted to the frames kept is the floor's (normal within 0.05 deg), the
    plain fit to all of them is tilted by degrees."""
    from tagtrail.geometry.joint.ground import fit_plane
    from tagtrail.stream.continuity import GROUND, robust_plane_frames

    rng = np.random.default_rng(4)
    a = np.linspace(0, 4.0, 200)
    C = _level_cameras(np.stack([np.cos(a), np.sin(a)], axis=1), a + np.pi / 2)
    bad = rng.choice(200, 10, replace=False)
    d = rng.uniform(-2.0, 2.0, (10, 3))  # the centres moved, off the floor's plane too
    d[:, 2] = rng.choice([-1.0, 1.0], 10) * rng.uniform(0.3, 1.0, 10)
    C[bad, :3, 3] -= np.einsum("fij,fj->fi", C[bad, :3, :3], d)
    keep = robust_plane_frames(C[:, :3, :3], C[:, :3, 3])
    assert not keep[bad].any() and keep.sum() == 190

    def tilt_deg(sel: np.ndarray) -> float:
        n = fit_plane(C[sel, :3, :3], C[sel, :3, 3], GROUND).n
        return float(np.degrees(np.arccos(min(1.0, abs(n[2])))))

    assert tilt_deg(keep) < 0.05 and tilt_deg(np.ones(200, bool)) > 1.0


def test_the_level_term_waits_for_a_history_that_tells_the_plane() -> None:
    """A straight drive leaves the plane's normal free to roll about the line: the smoother
    keeps the plane (per-frame height and tilt hold whatever the roll) but not the level term
    (tying the height along a normal tens of degrees off, it put the hall's camera 5 cm low
    in its U-turn). Once the history turns it holds the level term too."""
    from tagtrail.geometry.joint.ground import GroundLevel
    from tagtrail.stream.continuity import _Frame

    rng = np.random.default_rng(7)
    t = np.arange(240) / 30.0
    yaw = np.where(t < 4.0, 0.0, np.pi * np.clip(t - 4.0, 0.0, 2.0) / 2.0)  # then a U-turn
    step = 0.6 / 30.0 * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(step[:-1], axis=0)])
    C = _level_cameras(xy, yaw)
    C[:, :3, 3] += rng.normal(scale=3e-4, size=(240, 3))  # the smoothed poses' sub-mm noise
    sm = Smoother(np.eye(4)[None], np.array([0.16]), SmootherSettings())
    told, planed = [], []
    for k in range(len(t)):
        sm._note(int(t[k] * 1e9), C[k, :3, :3], C[k, :3, 3])
        told.append(sm.level)
        planed.append(sm.plane is not None)
    told_at = np.flatnonzero(told)
    assert planed.index(True) < 60  # the plane from the first metre on, the level term not
    assert 4.0 < t[told_at[0]] < 5.5  # not on the straight 2.4 m, soon into the turn
    assert all(told[told_at[0] :])  # (the history keeps the turn)
    sm.frames.extend(
        _Frame(
            int(t[k] * 1e9), np.zeros(0, np.int64), np.zeros((0, 4, 2)), C[k, :3, :3], C[k, :3, 3]
        )
        for k in range(3)
    )
    assert any(isinstance(p, GroundLevel) for p in sm._priors(list(sm.frames)))
    sm.level = False
    assert not any(isinstance(p, GroundLevel) for p in sm._priors(list(sm.frames)))


@pytest.mark.parametrize(("ground", "held"), [("auto", False), ("plane", True)])
def test_a_hand_held_history_is_not_held_to_a_plane(ground: str, held: bool) -> None:
    """A camera carried by hand (+-10 cm up and down, +-5 deg of roll and pitch) leaves any
    plane: with ``ground: auto`` the smoother holds no ground prior (nor the drive's), as the
    offline planarity test decides; ``ground: plane`` holds it all the same."""
    from tagtrail.geometry.joint import JointSettings
    from tagtrail.geometry.se3 import R_from_rotvec

    rng = np.random.default_rng(3)
    t = np.arange(240) / 30.0
    yaw = 0.4 * np.sin(0.7 * t)
    step = 0.5 / 30.0 * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(step[:-1], axis=0)])
    C = _level_cameras(xy, yaw)
    wobble = R_from_rotvec(rng.normal(scale=np.radians(5.0), size=(240, 3)))
    C[:, :3, :3] = wobble @ C[:, :3, :3]
    C[:, :3, 3] = np.einsum("fij,fj->fi", wobble, C[:, :3, 3])
    C[:, :3, 3] -= np.einsum(
        "fij,fj->fi", C[:, :3, :3], [0.0, 0.0, 1.0] * rng.normal(scale=0.1, size=(240, 1))
    )
    settings = SmootherSettings(joint=JointSettings(ground=ground))  # type: ignore[arg-type]
    sm = Smoother(np.eye(4)[None], np.array([0.16]), settings)
    for k in range(len(t)):
        sm._note(int(t[k] * 1e9), C[k, :3, :3], C[k, :3, 3])
    assert sm.fitted
    assert (sm.plane is not None) == held
    if not held:
        assert sm.mount is None and not sm.level


@pytest.mark.parametrize(("sideways", "kept"), [(False, True), (True, False)])
def test_the_drive_prior_holds_a_wheeled_robot_only(sideways: bool, kept: bool) -> None:
    """A robot weaving along (the camera 8 cm ahead of its turning centre): the smoother keeps
    the wheeled-drive prior with the mount fitted on the history (lever arm 8 cm); a camera
    that slides sideways as it goes (a mecanum base) strains it: dropped."""
    tf = np.arange(150 * 30) / 900.0  # the base integrated at 900 Hz, the camera at 30
    yaw_f = 0.6 * tf - 0.8 * np.cos(1.5 * tf)  # a weave: a steady arc cannot tell the lever
    mid = 0.5 * (yaw_f[1:] + yaw_f[:-1])  # arm from the mount's yaw
    step = 0.5 / 900.0 * np.stack([np.cos(mid), np.sin(mid)], axis=1)  # 0.5 m/s
    base_f = np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    t, yaw, base = tf[::30], yaw_f[::30], base_f[::30]
    fwd = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    xy = base + 0.08 * fwd
    if sideways:
        xy = xy + 0.3 * np.stack([-np.sin(yaw), np.cos(yaw)], axis=1) * np.sin(3 * t)[:, None]
    C = _level_cameras(xy, yaw)
    sm = Smoother(np.eye(4)[None], np.array([0.16]), SmootherSettings())
    for k in range(len(t)):
        sm._note(int(t[k] * 1e9), C[k, :3, :3], C[k, :3, 3])
    assert sm.plane is not None
    assert (sm.mount is not None) == kept
    if kept:
        assert sm.mount is not None and sm.mount.lever_m == pytest.approx(0.08, abs=1e-3)


@pytest.mark.parametrize("lever_m", [None, 0.08, -0.06])
def test_a_known_mount_holds_the_lever_arm_from_the_start(lever_m: float | None) -> None:
    """A robot weaving gently along a corridor never turns enough to tell the camera's lever
    arm: fitted, it stays 0; given (``--camera-forward``, the profile's; negative: a camera
    behind the turning centre) it is held from the first fit, and the mount's yaw is fitted on
    it."""
    t = np.arange(240) / 30.0
    yaw = 0.03 * np.sin(1.5 * t)  # ~0.15 rad turned in all
    step = 1.2 / 30.0 * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    base = np.concatenate([np.zeros((1, 2)), np.cumsum(step[:-1], axis=0)])
    xy = base + (lever_m or 0.08) * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    C = _level_cameras(xy, yaw)
    sm = Smoother(np.eye(4)[None], np.array([0.16]), SmootherSettings(lever_m=lever_m))
    for k in range(len(t)):
        sm._note(int(t[k] * 1e9), C[k, :3, :3], C[k, :3, 3])
    assert sm.mount is not None
    assert sm.mount.lever_m == (0.0 if lever_m is None else lever_m)
    # the camera looks along the robot's heading: its forward axis is the optical axis
    assert sm.mount.g[2] > np.cos(np.radians(0.2 if lever_m else 2.0))


def test_wheel_odometry_joins_the_window(noisy: Path) -> None:
    """With the recording's /odom fed (``--odom-key``) the odometry prior joins each window
    once the plane is known (its scale read against the history: the simulator's wheels read
    1-3 % long), and the live poses are no worse than without (measured 2.15 vs 2.20 mm here;
    on the corridor of far tags 6.3 vs 8.4 mm, bench/LIVE_POSE.md)."""
    from tagtrail.stream.continuity import LiveOdometry

    gt = read_trajectory(noisy / "ground_truth" / "trajectory.csv").set_index("t_ns")
    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections", "/odom"])
    loc = Localizer(tags)
    fed, bare = _live(loc), _live(loc)
    odo = next(p for p in fed.smoother.extra if isinstance(p, LiveOdometry))
    joined = 0
    errs: dict[str, list[float]] = {"fed": [], "bare": []}
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k == "odom":
            fed.on_odometry(p)
        elif k == "detections":
            for name, live in (("fed", fed), ("bare", bare)):
                loc.smooth(live)
                out = dict(loc.on_detections(p))
                errs[name].append(_err(out["tag_only_pose"], gt))
            fr = fed.smoother.frames
            t_s = np.array([(f.t_ns - fr[0].t_ns) * 1e-9 for f in fr])
            joined += odo(t_s, [f.t_ns for f in fr]) is not None
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errs.items()}
    assert joined > 0.6 * N_FRAMES
    assert 1.0 < odo.scales[0] < 1.05
    assert fed.dead.errors == (*odo.scales, *odo.yaw)  # the dead reckoning takes them off
    assert rms["fed"] <= 1.05 * rms["bare"], rms


def test_a_frame_behind_the_odometry_carries_its_fix_to_the_newest_pose(noisy: Path) -> None:
    """A camera stamped at exposure delivers each frame ~20 ms late, after odometry of later
    stamps: those poses left first (dead-reckoned from the previous fix). The frame's fix is
    then carried by the odometry to the last pose's stamp and published for it again (in
    time order; before, the fix was dropped), its source ``tags`` and its fix age the
    carry's."""
    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections", "/odom"])
    loc = Localizer(tags)
    live = _live(loc)
    loc.smooth(live)
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    late_ns = 20_000_000
    order = sorted(
        range(len(m.keys)),
        key=lambda i: int(m.t_ns[i]) + (late_ns if m.keys[i] != "odom" else 0),
    )
    stamps: list[int] = []
    carried: list[tuple[int, float]] = []  # (stamp, fix age)
    frames = 0
    for i in order:
        k, p = m.keys[i], m.payloads[i]
        if k == "camera_info":
            loc.on_camera_info(p)
            continue
        if k == "odom":
            out = dict(live.on_odometry(p))
        else:
            before = live.counts["tags"]
            try:
                out = dict(loc.on_detections(p))
            except DropError:
                continue
            frames += live.counts["tags"] - before
            assert out, "a frame's fix is never dropped"
        if not out:
            continue
        q = codec.decode_pose(out["tag_only_pose"])
        stamps.append(q.sec * 1_000_000_000 + q.nanosec)
        state = json.loads(out["localize/state"])
        if k == "odom":
            continue
        head = codec.deserialize(p, "apriltag_msgs/msg/AprilTagDetectionArray").header.stamp
        assert state["source"] == "tags"
        if stamps[-1] != head.sec * 1_000_000_000 + head.nanosec:
            assert stamps[-1] > head.sec * 1_000_000_000 + head.nanosec
            assert state["fix_age_s"] > 0
            carried.append((stamps[-1], state["fix_age_s"]))
    assert np.all(np.diff(stamps) >= 0)  # in time order (a carried fix: the same stamp again)
    assert len(carried) > 0.5 * frames and live.counts["carried"] == len(carried)
    assert max(c[1] for c in carried) < late_ns * 1e-9


def test_the_pose_leaves_before_the_window_is_re_solved(
    noisy: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With ``step_first`` (the default) a frame's pose is the filter's step on the last solve
    and the window's re-solve waits for ``settle`` (the node's, once the pose is out; else the
    next frame's); the poses are as good as the re-solve-first ones (measured here 2.10 vs
    2.13 mm RMS; the step starts from the motion's extrapolation, tests/geometry/test_newest.py),
    and the frame's own pose (the per-frame multi-tag PnP) is not computed for it."""
    gt = read_trajectory(noisy / "ground_truth" / "trajectory.csv").set_index("t_ns")
    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections"])
    loc = Localizer(tags)
    lives = {step: _live(loc, SmootherSettings(step_first=step)) for step in (True, False)}
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    errs: dict[bool, list[float]] = {True: [], False: []}
    pending = 0
    posed = {True: 0, False: 0}  # frames posed on their own (multi-tag PnP) for each
    calls = [0]
    frame_poses = localize.frame_poses

    pnp_frames = localize.pnp_frames

    def counted(*a: Any, **kw: Any) -> Any:
        calls[0] += 1
        return frame_poses(*a, **kw)

    def counted_pnp(*a: Any, **kw: Any) -> Any:
        calls[0] += 1
        return pnp_frames(*a, **kw)

    monkeypatch.setattr(localize, "frame_poses", counted)
    monkeypatch.setattr(localize, "pnp_frames", counted_pnp)
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k != "detections":
            continue
        for step, live in lives.items():
            loc.smooth(live)
            before = calls[0]
            out = dict(loc.on_detections(p))
            posed[step] += calls[0] - before
            errs[step].append(_err(out["tag_only_pose"], gt))
            sm = live.smoother
            if step and sm._pending is not None:
                pending += 1
                t_last = sm.frames[-1].t_ns
                live.settle()
                assert sm._pending is None and sm._job is None
                assert sm._last is not None and sm._last[0] == t_last
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errs.items()}
    assert pending >= N_FRAMES - 3  # every frame once the window has two solved ones
    # the step starts from the motion's extrapolation: the frame's own pose is not computed
    assert posed[False] == N_FRAMES and posed[True] <= 3, posed
    assert rms[True] <= 1.05 * rms[False], rms
    assert errs[True] != errs[False]  # the step did answer


def _until_idle(bg: Any, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not bg.idle() and time.monotonic() < deadline:
        time.sleep(0.005)


def test_the_background_re_solve_gives_the_same_poses(noisy: Path) -> None:
    """The window's re-solve handed to the background process once the pose is out
    (``dispatch``, as the node does) and taken by a later ``dispatch`` or the next frame — or
    computed by it when not back yet — gives the poses of re-solving in the foreground (a pure
    function of the window taken when the pose left)."""
    from tagtrail.stream.background import Background
    from tagtrail.stream.continuity import RESOLVE

    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections"])
    loc = Localizer(tags)
    lives = [
        LivePoses(
            # no time budget: a window cut by a slow solve on one side only is not the point
            Smoother(loc.world_T_tag, loc.size_m, SmootherSettings(budget_ms=math.inf)),
            DeadReckoning(),
            "tag_only_pose",
            "localize",
            "map",
        )
        for _ in range(2)
    ]
    bg = lives[0].smoother.background = Background(RESOLVE, "test")
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    poses: list[list[bytes]] = [[], []]
    try:
        dets = [q for k, q in zip(m.keys, m.payloads, strict=True) if k == "detections"]
        for i, p in enumerate(dets):
            for j, live in enumerate(lives):
                loc.smooth(live)
                poses[j].append(dict(loc.on_detections(p))["tag_only_pose"])
                if j == 0 and i % 4 == 1:  # to an idle child, back before the next frame
                    _until_idle(bg)
                    live.dispatch()
                    _until_idle(bg)
                elif j == 0 and i % 4 == 3:  # back, and taken between messages by a later
                    _until_idle(bg)  # dispatch (the node asks again while it says it waits)
                    assert live.dispatch()  # handed over: to be asked again
                    _until_idle(bg)
                    assert not live.dispatch()  # taken: nothing to wait for
                    assert live.smoother._job is None  # the next frame has nothing to do
                elif j == 0:  # the next frame mostly computes it itself
                    live.dispatch()
                else:
                    live.settle()
    finally:
        bg.close()
    a = np.array([_pose7(x) for x in poses[0]])
    b = np.array([_pose7(x) for x in poses[1]])
    assert np.abs(a - b).max() < 1e-12
    assert bg.counts["used"] >= N_FRAMES // 3, bg.counts


def test_the_step_takes_the_odometry_on_to_the_new_frame_but_not_across_a_gap() -> None:
    """A frame handled at once has no odometry of its time yet (50 Hz, stamps 2-8 ms late):
    the stream carried on at its last rate up to ``EXTEND_S`` gives the step its term on the
    new frame. A stream that stopped further back (a gap) gives none (the steps before it
    are the window's, not the step's)."""
    from tagtrail.geometry.joint.ground import Plane
    from tagtrail.stream.continuity import LiveOdometry

    sm = Smoother(np.eye(4)[None], np.array([0.1]))
    sm.plane = Plane(np.array([0.0, -1.0, 0.0]), 0.0, np.array([0.0, 1.0, 0.0]))
    sm._travel = sm.s.plane_after_m  # the first metre travelled: the odometry joins
    odo = LiveOdometry(sm, DeadReckoning(latency_s=0.0))
    for t in range(980_000_000, 1_040_000_001, 20_000_000):  # up to 1.04 s
        odo.dead.add_odometry(t, 0.3 * (t * 1e-9 - 1.0), 0.0, 0.0)
    for newest_ns, reaches in ((1_066_000_000, True), (1_090_000_000, False)):
        assert (newest_ns - 1_040_000_000 <= LiveOdometry.EXTEND_S * 1e9) is reaches
        frames_ns = [1_000_000_000, 1_033_000_000, newest_ns]
        got = odo(np.array([(t - frames_ns[0]) * 1e-9 for t in frames_ns]), frames_ns)
        assert got is not None, newest_ns
        assert got.prior.j.tolist() == ([0, 1] if reaches else [0])


def test_the_odometry_read_in_scalars_is_the_window_prior_s_reading() -> None:
    """``DeadReckoning.reading`` (a frame's step, on arrival) reads what the window's prior
    reads from the same samples (``LiveOdometry._odometry``, carried on by ``Odometry.
    extended``, ``relative``): within the samples, past the last (carried on, both times
    too), across the yaw's wrap at +-pi; None beyond the carry or before the samples."""
    from tagtrail.geometry.joint.odometry import Odometry

    rng = np.random.default_rng(3)
    dead = DeadReckoning(latency_s=0.0)
    t = 1_000_000_000 + np.cumsum(rng.integers(15_000_000, 25_000_000, 40))
    yaw = np.pi - 0.4 + np.cumsum(rng.uniform(0.0, 0.06, 40))  # through +pi
    x, y = np.cumsum(rng.uniform(0, 0.01, 40)), np.cumsum(rng.uniform(-0.01, 0.01, 40))
    dead.odo.extend(
        (int(a), float(b), float(c), math.remainder(float(d), math.tau))  # wrapped, as read
        for a, b, c, d in zip(t, x, y, yaw, strict=True)
    )
    ext = 40_000_000
    for since, t0, t1 in [
        (t[5], t[5] + 3_000_000, t[7] + 1_000_000),  # within
        (t[1], t[2] + 1_000_000, t[-5] + 2_000_000),  # across the wrap
        (t[20], t[25] + 9_000_000, t[-1] + 30_000_000),  # the new frame past the last
        (t[-3], t[-1] + 5_000_000, t[-1] + 30_000_000),  # both past it
    ]:
        got = dead.reading(int(t0), int(t1), int(since), ext)
        k = int(np.searchsorted(t, since, side="right")) - 1
        base = int(since)
        odo = Odometry((t[k:] - base) * 1e-9, x[k:], y[k:], np.unwrap(yaw[k:]))
        odo = odo.extended((t1 - base) * 1e-9, ext * 1e-9)
        want = odo.relative(np.array([(t0 - base) * 1e-9]), np.array([(t1 - base) * 1e-9]))[0]
        assert got is not None and np.allclose(got, want, rtol=0, atol=1e-12), (got, want)
    assert dead.reading(int(t[-3]), int(t[-1] + ext + 1_000_000), int(t[-3]), ext) is None
    assert dead.reading(int(t[0] - 1), int(t[2]), int(t[0]), ext) is None


def test_the_step_s_odometry_term_is_the_window_prior_s(noisy: Path) -> None:
    """The odometry's term in a frame's step (``LiveOdometry.ahead``, its Jacobians at the
    start, then ``ahead_rows`` with the reading on arrival) is the window's odometry prior's
    term on that frame (``LiveOdometry(...)``'s ``FixedOdometry`` through ``prior_rows``, as
    the step took it before): residuals and Jacobians within 1e-9 on every frame of a
    recording once the plane is fitted, the odometry carried on to each frame's stamp."""
    from tagtrail.geometry.joint.newest import prior_rows

    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections", "/odom"])
    loc = Localizer(tags)
    live = _live(loc)
    loc.smooth(live)
    sm = live.smoother
    odo = sm.extra[0]
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    compared, worst = 0, 0.0
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k == "odom":
            dict(live.on_odometry(p))
            continue
        if k != "detections":
            continue
        t_new = codec.deserialize(p, "apriltag_msgs/msg/AprilTagDetectionArray").header.stamp
        t_ns = t_new.sec * 1_000_000_000 + t_new.nanosec
        sm.settle()
        start = sm._extrapolate(t_ns) if len(sm.frames) >= 2 else None
        if start is not None and sm.plane is not None:
            a, b = sm.frames[-2], sm.frames[-1]
            t_s = np.array([0.0, (b.t_ns - a.t_ns) * 1e-9, (t_ns - a.t_ns) * 1e-9])
            prior = odo(t_s, [a.t_ns, b.t_ns, t_ns])
            want = (
                prior_rows(np.stack([a.R, b.R, start[0]]), np.stack([a.t, b.t, start[1]]), [prior])
                if prior is not None and (prior.prior.j == 1).any()  # a step into the frame
                else None
            )
            got = odo.ahead_rows(odo.ahead(a, b, start), t_ns, np.zeros(6))
            assert (got is None) == (want is None), t_ns
            if got is not None and want is not None:
                compared += 1
                worst = max(
                    worst, *(float(np.abs(x - y).max()) for x, y in zip(got, want, strict=True))
                )
        dict(loc.on_detections(p))
    assert compared > 0.5 * N_FRAMES and worst < 1e-9, (compared, worst)


@pytest.mark.parametrize("jitter_ns", [0, 300, 150_000])
def test_the_step_taken_ahead_gives_the_pose_taken_on_arrival(noisy: Path, jitter_ns: int) -> None:
    """The priors' terms of the next frame's step, taken once the window is re-solved at the
    stamp one interval on (``step_ahead``), give the poses of taking them on the frame's
    arrival: within 1e-8 at the recording's stamps (30 Hz: the interval 1 ns off every third
    frame, the only difference) and within 1 um with stamps 0.3 us off their period (moved on
    their linear model); stamps off by more than ``AHEAD_TOL_NS`` (a host clock's 0.15 ms)
    take them on arrival (but the few that happen to fall within it), and after
    ``AHEAD_MISSES`` such frames in a row it is taken ahead every ``AHEAD_RETRY``-th frame only."""
    from tagtrail.stream.continuity import AHEAD_MISSES, AHEAD_RETRY, AHEAD_TOL_NS

    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections", "/odom"])
    loc = Localizer(tags)
    events: list[tuple] = []  # the frames' on_frame arguments and the odometry, in order
    grab = _live(loc)
    real = grab.on_frame
    grab.on_frame = lambda *a: (events.append(a), real(*a))[1]  # type: ignore[method-assign]
    loc.smooth(grab)
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k == "detections":
            dict(loc.on_detections(p))
        elif k == "odom":
            events.append((p,))
    rng = np.random.default_rng(1)
    # (no time budget: a window cut by a slow solve on one side only is not the point)
    lives = [_live(loc, SmootherSettings(step_ahead=a, budget_ms=math.inf)) for a in (True, False)]
    odo = lives[0].smoother.extra[0]  # the odometry's term in the step: its uses counted
    real_rows, odo_rows = odo.ahead_rows, [0]

    def counted(*args: Any) -> Any:
        got = real_rows(*args)
        odo_rows[0] += got is not None
        return got

    odo.ahead_rows = counted
    poses: list[list[tuple[float, ...]]] = [[], []]
    for ev in events:
        if len(ev) == 1:
            for live in lives:
                dict(live.on_odometry(ev[0]))
            continue
        t_ns, own, obs, camera = ev
        t = t_ns + int(rng.integers(-jitter_ns, jitter_ns + 1))
        for live, out in zip(lives, poses, strict=True):
            out.append(_pose7(dict(live.on_frame(t, own, obs, camera))["tag_only_pose"]))
            live.settle()
    a, b = np.array(poses[0]), np.array(poses[1])
    used = lives[0].smoother.ahead_used
    assert lives[1].smoother.ahead_used == 0
    if 4 * jitter_ns <= AHEAD_TOL_NS:  # (the stamp one interval on: three stamps off)
        assert used > 0.9 * N_FRAMES
        assert odo_rows[0] > 0.5 * N_FRAMES  # (once the plane is fitted: the odometry's term)
        assert np.abs(a - b).max() < (1e-8 if jitter_ns == 0 else 1e-6)
    else:
        assert used < 0.05 * N_FRAMES and np.abs(a - b).max() < 1e-6  # (a few by chance)
        taken = lives[0].smoother.ahead_taken
        assert taken <= 2 * AHEAD_MISSES + N_FRAMES / AHEAD_RETRY < 0.2 * N_FRAMES, taken


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """The ``ground.json`` of a mapping run: the offline joint solve of another recording of the
    circle (seed 6) against the map, as ``optimize`` reports and exports it."""
    import dataclasses

    from tagtrail.schemas.documents import GroundSummary
    from tagtrail.stream.continuity import HeldGround

    rec = simulate(
        "circle",
        tmp_path_factory.mktemp("mapping"),
        frames=N_FRAMES,
        detections=True,
        corner_noise_px=0.3,
        seed=6,
    )["circle"]
    tags = read_tag_map(rec / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(rec, ["/camera_info", "/detections"])
    loc = Localizer(tags)
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    obs = []
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k == "detections":
            q = codec.decode_pose(loc.on_detections(p)[0][1])
            assert loc._last_obs is not None
            obs.append((q.sec * 10**9 + q.nanosec, *loc._last_obs))
    _, sol = _offline(loc, obs)
    assert sol.ground is not None
    doc = GroundSummary.model_validate(dataclasses.asdict(sol.ground)).known()
    assert doc is not None and doc.forward_camera is not None  # the plane and the mount
    return HeldGround.of(doc)


def _first_metre(noisy: Path, held: Any) -> tuple[LivePoses, np.ndarray, np.ndarray]:
    """The live poses' errors on the noisy circle with ``held`` (or None), and whether the
    frame came before a smoother without it had fitted its own plane."""
    gt = read_trajectory(noisy / "ground_truth" / "trajectory.csv").set_index("t_ns")
    tags = read_tag_map(noisy / "ground_truth" / "tag_map.yaml")[0]
    m = bag_messages(noisy, ["/camera_info", "/detections"])
    loc = Localizer(tags)
    live, bare = _live(loc, SmootherSettings(ground=held)), _live(loc)
    loc.on_camera_info(m.payloads[m.keys.index("camera_info")])
    errs, early = [], []
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k == "detections":
            early.append(bare.smoother.plane is None)
            loc.smooth(bare)
            loc.on_detections(p)
            loc.smooth(live)
            errs.append(_err(dict(loc.on_detections(p))["tag_only_pose"], gt))
    return live, np.array(errs), np.array(early)


def test_a_mapping_runs_ground_is_held_from_the_first_frame(noisy: Path, mapped: Any) -> None:
    """``--ground`` (``ground.json``): the mapping run's plane and mount held from the first
    frame, where the smoother would wait for 1 m of travel to fit them to its own history;
    the poses of that first metre are better for it, and the rest no worse (the mapping run
    is another recording, seed 6, of the circle; errors against the simulator's truth;
    measured: 1.77 mm RMS before the plane's fit against 2.35, all frames 1.75 against 1.84)."""
    live, held, early = _first_metre(noisy, mapped)
    _, bare, _ = _first_metre(noisy, None)
    rms = {
        k: float(np.sqrt(np.mean(np.square(v))))
        for k, v in (
            ("held_early", held[early]),
            ("bare_early", bare[early]),
            ("held", held),
            ("bare", bare),
        )
    }
    assert early.sum() >= 30  # the circle's first metre: over a second of frames
    assert live.smoother.held is mapped and live.smoother.plane is mapped.plane
    assert live.smoother.mount is mapped.mount
    assert rms["held_early"] < 0.8 * rms["bare_early"], rms
    assert rms["held"] <= rms["bare"], rms


def test_a_ground_the_run_sits_off_is_dropped(
    noisy: Path, mapped: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """Another robot's (its camera 10 cm higher): dropped, with a warning, from the history's
    tenth pose; the plane is then fitted to the run's own poses, as without one."""
    from tagtrail.geometry.joint.ground import Plane
    from tagtrail.stream.continuity import HeldGround

    p = mapped.plane
    off = HeldGround(Plane(p.n, p.d + 0.1, p.u), mapped.mount)
    with caplog.at_level("WARNING", logger="tagtrail.stream"):
        live, errs, _ = _first_metre(noisy, off)
    assert live.smoother.held is None
    sits = re.search(r"sits ([0-9.]+) cm off it", live.smoother.dropped)
    assert sits is not None and 9.0 < float(sits.group(1)) < 11.0, live.smoother.dropped
    assert any("ground plane (--ground) dropped" in r.getMessage() for r in caplog.records)
    assert live.smoother.plane is not None and abs(live.smoother.plane.d - p.d) < 0.005
    assert float(np.sqrt(np.mean(errs[-100:] ** 2))) < 0.005


def test_a_mapping_runs_mount_off_the_given_lever_arm_is_not_held(
    mapped: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """A mapping run's mount whose lever arm is not the one given (``--camera-forward``) is not
    held (a pure arc cannot tell the lever arm from the camera's yaw: the rendered circle's
    solved -1.28 m), said in a warning; its plane is. Within 2 cm of it, both are."""
    from tagtrail.geometry.joint.drive import Mount
    from tagtrail.stream.continuity import HeldGround

    assert mapped.mount is not None
    lever = mapped.mount.lever_m
    for given, held in ((lever + 0.05, False), (lever + 0.01, True)):
        caplog.clear()
        ground = HeldGround(mapped.plane, Mount(mapped.mount.g, lever))
        with caplog.at_level("WARNING", logger="tagtrail.stream"):
            sm = Smoother(
                np.eye(4)[None], np.array([0.1]), SmootherSettings(lever_m=given, ground=ground)
            )
        assert sm.plane is mapped.plane and sm.level
        assert (sm.mount is ground.mount) is held and (sm.mount is None) is not held
        said = [
            r.getMessage()
            for r in caplog.records
            if "mount (--ground) is not held" in r.getMessage()
        ]
        assert len(said) == (0 if held else 1), said

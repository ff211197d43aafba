"""``tagtrail simulate follow --out DIR``: the closed loop — simulated LIMO, real nodes, zenoh.

The simulated LIMO (:mod:`tagtrail.sim.limo`) publishes ``detections`` (apriltag_msgs) and
``camera_info`` — or, ``images=True``, rendered 640×480 rgb8 ``camera/color/image_raw`` with
``camera/color/camera_info``, detected by ``stream localize`` (30 Hz) —
and ``odom`` (50 Hz) on a zenoh peer listening on 127.0.0.1 and obeys
``cmd_vel``; ``stream localize`` → ``stream relocalize`` → ``stream follow`` run as their own
processes, chained on loopback ports (sim ← localize ← relocalize ← follow, follow → sim), as on
a robot. Simulated time is wall time (real time on loopback). The camera exposes on its own 30 Hz
clock and stamps each frame with its exposure (as a driver with the sensor's timestamps); the
wheels are read on a 50 Hz clock and each reading is stamped when published, 2-8 ms later (the
LIMO's driver, NOTES). A step of the simulation publishes what its sensors took since the last;
a frame's detections go out a step (~4 ms) after its ``camera_info``, as a detector's output
follows the camera driver's message.

The reference (default): a figure eight (lemniscate of Bernoulli, a = 1.8 m: 9.0 m, crossing
itself at its centre, tightest radius 0.6 m) in a 4.8 × 3.6 m room with 26 wall tags, opened
0.4 m short of its start so it is a path with an end; its ground truth (camera poses at 30 Hz,
``tag_map.yaml``, ``scene.yaml``) is written to ``DIR/ground_truth/`` and is both the map
``localize`` uses and the reference ``relocalize`` follows. ``--reference`` takes another
trajectory in the same world (e.g. that recording mapped by the pipeline).

Outputs: ``follow.csv`` (50 Hz: t_s, the base's true x, y, yaw in the scene frame, the camera's
true cross-track — the same tracker on the true pose — and the measured one, D, phi from the
state JSON, the commanded v and omega), ``follow_summary.json`` (``converged_s``: first time
|true cross-track| < 5 cm; ``cross_track_rms_m`` / ``_max_m`` from 5 s on (the issue's
allowance to converge; from ``converged_s`` if later), ``from_converged`` the same from
``converged_s``, ``crossing`` within 0.5 m of the figure eight's centre; ``completed``: stopped
within 0.15 m of the end; detections→Twist latency: sim publishes a frame with a tag in view →
first Twist back, from 1 s on, the first second's maximum (the nodes' warm-up) apart),
``follow.png``.
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from tagtrail.errors import SpecError
from tagtrail.geometry.association import PathTracker, TrackParams
from tagtrail.geometry.reference_path import ReferencePath, reference_plane
from tagtrail.geometry.se3 import compose
from tagtrail.io.layouts import atomic_write_text, read_trajectory
from tagtrail.schemas.artifacts import poses
from tagtrail.sim import limo
from tagtrail.sim.render import Renderer
from tagtrail.sim.scenarios import SimOptions, _tags
from tagtrail.sim.scene import (
    Scene,
    box_walls,
    resample_path,
    scene_T_cam_planar,
    stamps_ns,
    upright_pose,
)
from tagtrail.sim.simulate import write_ground_truth
from tagtrail.stream.follow import decode_twist
from tagtrail.stream.node import collect_due, collections_between_messages
from tagtrail.stream.session import make_config

PLANE = "xz"  # the floor of the anchor's frame (world y up: n = −y points down)
COLUMNS = (
    "t_s,x,y,yaw_rad,true_cross_track_m,cross_track_m,distance_m,heading_error_deg,v_mps,omega_rps"
)
CONVERGED_M = 0.05
IMAGE_KEY, IMAGE_INFO_KEY = "camera/color/image_raw", "camera/color/camera_info"  # the LIMO's
WARMUP_S = 1.0  # latency is counted from then on (the first second's maximum apart)
SETTLE_S = 5.0  # the allowance to converge: RMS and max are taken after it
# The room's short walls at x = ±2.4 m: every pose of the figure eight sees >= 2 tags but one
# frame (1) within the detections' 3.5 m range. With walls at ±3 m two stretches of 1.2 s saw 0-1
# tag (30 frames none): per-frame localize had no pose there, the follower stopped after 0.5 s
# as it must, and a robot that stopped inside never saw a tag again (parked for good: the
# closed-loop test's completed=false, RMS ~ max ~ 1.2 cm).
ROOM_X = 2.4


def eight_poly(a: float = 1.8, gap_m: float = 0.4, k: int = 4000) -> np.ndarray:
    """The figure eight from its right tip (heading +y), stopped ``gap_m`` short of closing."""
    t = np.linspace(0.0, 2 * np.pi, k)
    d = 1 + np.sin(t) ** 2
    xy = np.stack([a * np.cos(t) / d, a * np.sin(t) * np.cos(t) / d], -1)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    return np.asarray(xy[s <= s[-1] - gap_m])


def eight_scene(opts: SimOptions) -> Scene:
    """The reference recording: the figure eight driven at ``opts.speed_mps``, ``opts.fps``."""
    poses_: list[np.ndarray] = []
    for x in np.arange(-2.1, 2.11, 0.6):  # long walls, 8 tags each
        poses_.append(
            upright_pose(np.array([x, 1.8, 0.30 + 0.08 * (len(poses_) % 3)]), np.array([0.0, -1.0]))
        )
        poses_.append(
            upright_pose(np.array([x, -1.8, 0.30 + 0.08 * (len(poses_) % 3)]), np.array([0.0, 1.0]))
        )
    for y in np.arange(-1.2, 1.21, 0.6):  # short walls, 5 tags each
        poses_.append(upright_pose(np.array([ROOM_X, y, 0.34]), np.array([-1.0, 0.0])))
        poses_.append(upright_pose(np.array([-ROOM_X, y, 0.38]), np.array([1.0, 0.0])))
    tags, anchor = _tags(poses_, opts)
    poly = eight_poly()
    _, _, length = resample_path(poly, 2, False)
    n = max(2, int(round(length / opts.speed_mps * opts.fps)))
    xy, yaw, _ = resample_path(poly, n, False)
    info = {
        "scenario": "follow",
        "path": "figure eight (lemniscate, a = 1.8 m)",
        "path_length_m": length,
        "frames": n,
    }
    return Scene(
        "reference",
        opts.camera,
        tags,
        box_walls(-ROOM_X, -1.8, ROOM_X, 1.8, 2.5),
        anchor,
        scene_T_cam_planar(xy, yaw, opts.mount),
        stamps_ns(n, opts.fps),
        info=info,
    )


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _Proc:
    """A ``python -m tagtrail.stream.cli`` node whose output is collected."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.p = subprocess.Popen(
            [sys.executable, "-m", "tagtrail.stream.cli", *args],
            cwd=cwd,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, text: str, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while not any(text in x for x in self.lines):
            if self.p.poll() is not None or time.monotonic() > deadline:
                raise SpecError(f"node did not start ({text!r}):\n" + "\n".join(self.lines))
            time.sleep(0.02)

    def stop(self) -> int | None:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
        try:
            return self.p.wait(10)
        except subprocess.TimeoutExpired:
            self.p.kill()
            self.p.wait(5)
            return None

    def stats(self) -> dict[str, Any] | None:
        for line in reversed(self.lines):
            if line.startswith("stats "):
                return dict(json.loads(line[6:]))
        return None


class _Truth:
    """The same tracker as relocalize's, on the true camera pose (world frame)."""

    def __init__(self, ref_csv: Path, world_T_scene: np.ndarray) -> None:
        P, R = poses(read_trajectory(ref_csv))
        self.path = ReferencePath(P, reference_plane(PLANE, P, R))
        self.tracker = PathTracker(self.path, TrackParams())
        self.length = float(self.tracker._s[-1])
        self.world_T_scene = world_T_scene

    def __call__(self, scene_T_cam: np.ndarray) -> tuple[float, float]:
        T = compose(self.world_T_scene, scene_T_cam)
        u, v, h = self.path.planar_point(*T[:3, 3].tolist(), *T[:3, 2].tolist())
        m = self.tracker.track(u, v, h)
        return m.cross_track_m, m.progress_m


IN_FLIGHT_S = 0.010  # the simulator's longest pause for a frame's Twist (run's loop)


def run(
    out: Path,
    *,
    reference: Path | None = None,
    start_offset_m: float = 0.3,
    start_heading_deg: float = 30.0,
    speed_mps: float = 0.3,
    blackout_s: float = 0.0,
    seed: int = 0,
    law: str = "stanley",
    images: bool = False,
    max_time_s: float | None = None,
    smooth: bool = False,
    low_latency: bool = True,
) -> dict[str, Any]:
    """Run the closed loop (module docstring); returns the summary written to
    ``out/follow_summary.json``. ``low_latency``: the nodes' links (and, with detections,
    the simulator's) on zenoh's low-latency transport (``--low-latency``; never an image's)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    opts = SimOptions(speed_mps=speed_mps, detections=True, seed=seed)
    scene = eight_scene(opts)
    gt = out / "ground_truth"
    write_ground_truth(gt, scene, "follow", opts)
    ref = Path(reference) if reference is not None else gt / "trajectory.csv"
    truth = _Truth(ref, scene.world_T_scene)
    rng = np.random.default_rng(seed)
    # the start: the reference's first base pose, start_offset_m to its left, turned left
    yaw0 = float(math.atan2(scene.scene_T_cam[0, 1, 2], scene.scene_T_cam[0, 0, 2]))
    p0 = scene.scene_T_cam[0, :2, 3] - opts.mount.forward_m * np.array(
        [math.cos(yaw0), math.sin(yaw0)]
    )
    left = np.array([-math.sin(yaw0), math.cos(yaw0)])
    x0, y0 = (p0 + start_offset_m * left).tolist()
    kin = limo.Kinematics(x=x0, y=y0, yaw=yaw0 + math.radians(start_heading_deg))
    odo = limo.WheelOdometry(rng)
    ports = [_port() for _ in range(3)]
    ep = [f"tcp/127.0.0.1:{p}" for p in ports]
    small = low_latency and not images  # the simulator's samples: no image on the transport
    session = zenoh.open(make_config("peer", listen=[ep[0]], low_latency=small))
    lock = threading.Lock()
    cmd = [0.0, 0.0]
    state: dict[str, Any] = {}
    lat: list[tuple[float, float]] = []  # (sim time of the frame, latency s)
    # the last frame published with a tag in view: its wall time and sim time, until a Twist
    # answers (a frame without a tag gives no pose: the follower's stop commands then answer
    # no frame)
    pending = [math.nan, math.nan]
    answered = threading.Event()  # the pending frame's Twist came
    t0 = time.monotonic()

    def on_cmd(sample: zenoh.Sample) -> None:
        try:
            v, w = decode_twist(sample.payload.to_bytes())
        except Exception:  # noqa: BLE001 - a bad command is ignored (the base keeps its own)
            return
        now = time.monotonic()
        with lock:
            cmd[:] = [v, w]
            kin.command(v, w, now - t0)
            if math.isfinite(pending[0]):
                lat.append((pending[1], now - pending[0]))
                pending[0] = math.nan
                answered.set()

    def published(seen: bool, t_sim: float) -> None:
        """A frame is out: its Twist is waited for (with a tag in view) from now."""
        with lock:
            pending[:] = [time.monotonic(), t_sim] if seen else [math.nan, math.nan]
            answered.clear()

    def on_state(sample: zenoh.Sample) -> None:
        try:
            doc = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with lock:
            state.update(doc)

    keys = (IMAGE_KEY, IMAGE_INFO_KEY) if images else ("detections", "camera_info")
    pubs = {k: session.declare_publisher(k, express=True) for k in (*keys, "odom")}
    renderer = Renderer(scene, opts.realism, seed=seed) if images else None
    subs = [session.declare_subscriber("cmd_vel", on_cmd)]
    procs: list[_Proc] = []
    rows: list[tuple[float, ...]] = []
    blind_from, completed, t_end_seen = math.nan, False, math.nan
    session_b = None
    quiet = ExitStack()
    try:
        common = ["--stats-period", "0"]
        fast = ["--low-latency"] if low_latency else []
        inputs = (
            # corners re-fitted by the gradient alone: detection, re-fit and pose within a
            # frame's 33 ms on 2 cores (the intensity-profile model adds ~3 ms a tag)
            [
                "--image-key",
                IMAGE_KEY,
                "--image-type",
                "raw",
                "--camera-info-key",
                IMAGE_INFO_KEY,
                "--refit-corners",
                "edges",
            ]
            if images
            else []
        )
        if smooth:  # the live smoother, the LIMO's odometry and its camera's lever arm
            forward = str(opts.mount.forward_m)
            inputs += ["--smooth", "--odom-key", "odom", "--camera-forward", forward]
        procs.append(
            _Proc(
                [
                    "localize",
                    "--map",
                    str(gt),
                    "--tag-size",
                    str(opts.tag_size_m),
                    *inputs,
                    "--listen",
                    ep[1],
                    "--connect",
                    ep[0],
                    *common,
                    *(fast if small else []),
                ],
                out,
            )
        )
        procs[-1].wait_for("localize: ready")
        procs.append(
            _Proc(
                [
                    "relocalize",
                    "--reference",
                    str(ref),
                    "--plane",
                    PLANE,
                    "--listen",
                    ep[2],
                    "--connect",
                    ep[1],
                    "--path-period",
                    "0",
                    *common,
                    *fast,
                ],
                out,
            )
        )
        procs[-1].wait_for("relocalize: ready")
        procs.append(
            _Proc(
                [
                    "follow",
                    "--profile",
                    "limo",
                    "--reference",
                    str(ref),
                    "--plane",
                    PLANE,
                    "--speed",
                    str(speed_mps),
                    "--law",
                    law,
                    "--connect",
                    ep[2],
                    "--connect",
                    ep[0],
                    *common,
                    *fast,
                ],
                out,
            )
        )
        procs[-1].wait_for("follow: ready")
        session_b = zenoh.open(make_config("peer", connect=[ep[2]], low_latency=low_latency))
        subs.append(session_b.declare_subscriber("relocalization/state", on_state))
        time.sleep(0.5)  # the links settle before the first frame
        limit = max_time_s or truth.length / speed_mps * 1.6 + blackout_s + 10.0
        # the garbage collected while no frame waits for its Twist, as in the nodes (a
        # collection in the simulator would delay the Twist's callback: latency not theirs)
        quiet.enter_context(collections_between_messages())
        # the Twist's callback waits for the interpreter's lock while the loop renders a
        # frame: hand it over within 0.5 ms instead of Python's 5 (a wait not the nodes')
        quiet.callback(sys.setswitchinterval, sys.getswitchinterval())
        sys.setswitchinterval(0.0005)
        t0, t0_ns = time.monotonic(), time.time_ns()
        t_sim, next_cam, next_odo, dt = 0.0, 0.0, 0.0, 0.005
        detected: list[tuple[bytes, bool]] = []
        while t_sim < limit:
            now = time.monotonic() - t0
            # the kinematics to now, through the camera's exposures and the wheels' readings on
            # their own clocks (30 Hz, 50 Hz; as the sensors: a frame's pose is the exposure's,
            # stamped with it; an odometry reading is stamped when published, 2-8 ms later)
            shots: list[tuple[float, np.ndarray]] = []
            reads: list[bytes] = []
            while t_sim < now:
                t_to = min(t_sim + dt, next_cam, next_odo)
                with lock:
                    kin.step(t_sim, t_to - t_sim)
                odo.step(kin.v, kin.omega, t_to - t_sim)
                t_sim = t_to
                if t_sim >= next_cam:
                    shots.append((t_sim, limo.camera_pose(scene, kin.x, kin.y, kin.yaw)))
                    next_cam = t_sim + 1 / opts.fps
                if t_sim >= next_odo:
                    lag_ns = limo.latency_ns(rng)  # stamp = publication time
                    reads.append(odo.message(t0_ns + round(t_sim * 1e9) + lag_ns))
                    next_odo = t_sim + 0.02
            # the detections of the last step's exposures, a step (~4 ms) after their
            # camera_info: a detector's time after the camera driver's message (apriltag_ros
            # takes longer), so the node has taken the CameraInfo before they arrive, as on a
            # robot; put at once after it, its handling lay on every frame's path (p99 +1 ms)
            for det, seen in detected:
                pubs["detections"].put(det)
                published(seen, t_sim)
            detected.clear()
            T = limo.camera_pose(scene, kin.x, kin.y, kin.yaw)
            ct, prog = truth(T)
            for t_shot, T_shot in shots:
                stamp_ns = t0_ns + round(t_shot * 1e9)
                if math.isnan(blind_from) and blackout_s > 0 and prog >= truth.length / 2:
                    blind_from = t_shot
                blind = blind_from <= t_shot < blind_from + blackout_s
                if renderer is not None:
                    img, info = limo.image(renderer, scene, T_shot, stamp_ns, rng, blind)
                    pubs[IMAGE_INFO_KEY].put(info)
                    pubs[IMAGE_KEY].put(img)
                    published(not blind, t_sim)
                else:
                    det, info, n_tags = limo.detections(scene, T_shot, stamp_ns, opts, rng, blind)
                    pubs["camera_info"].put(info)
                    detected.append((det, n_tags > 0))
            for read in reads:
                pubs["odom"].put(read)
            if reads:
                with lock:
                    s = dict(state)
                    c = list(cmd)
                rows.append(
                    (
                        t_sim,
                        kin.x,
                        kin.y,
                        kin.yaw,
                        ct,
                        *(
                            float(s.get(k, math.nan))
                            for k in ("cross_track_m", "distance_m", "heading_error_deg")
                        ),
                        *c,
                    )
                )
            if prog >= truth.length - 0.15 and abs(kin.v) < 0.005:
                if math.isnan(t_end_seen):
                    t_end_seen = t_sim
                elif t_sim - t_end_seen > 0.5:
                    completed = True
                    break
            else:
                t_end_seen = math.nan
            with lock:
                sent = pending[0]
            pause = sent + IN_FLIGHT_S - time.monotonic()  # (NaN: no frame in flight)
            if pause > 0:
                # a frame on its way through the nodes: the simulator keeps off the CPU until
                # its Twist (at most IN_FLIGHT_S): its own Python work (the next steps, the
                # truth's tracker) took a core and the interpreter's lock from the nodes and
                # the Twist's callback on 2 cores, latency that is no node's (a robot's
                # drivers are not on this interpreter); the kinematics catch up after
                answered.wait(pause)
            else:  # (a frame still in flight after the pause: its steps, not a spin)
                if math.isnan(sent):
                    collect_due()
                time.sleep(max(0.0, 0.004 - (time.monotonic() - t0 - now)))
    finally:
        quiet.close()
        codes = [p.stop() for p in reversed(procs)][::-1]
        for s_ in subs:
            s_.undeclare()  # type: ignore[no-untyped-call]
        for p in pubs.values():
            p.undeclare()  # type: ignore[no-untyped-call]
        if session_b is not None:
            session_b.close()  # type: ignore[no-untyped-call]
        session.close()  # type: ignore[no-untyped-call]
    data = np.array(rows, dtype=np.float64).reshape(-1, 10)
    summary = _summary(
        data,
        completed,
        truth.length,
        lat,
        blackout_s,
        blind_from,
        "images" if images else "detections",
    )
    summary["nodes"] = {
        n: {"exit": c, "stats": p.stats()}
        for n, c, p in zip(("localize", "relocalize", "follow"), codes, procs, strict=False)
    }
    summary["params"] = {
        "start_offset_m": start_offset_m,
        "start_heading_deg": start_heading_deg,
        "speed_mps": speed_mps,
        "blackout_s": blackout_s,
        "seed": seed,
        "law": law,
        "reference": str(ref),
        "plane": PLANE,
        "input": "images" if images else "detections",
        "smooth": smooth,
        "low_latency": low_latency,
    }
    summary = dict(_rounded(summary))
    np.savetxt(out / "follow.csv", data, delimiter=",", header=COLUMNS, comments="", fmt="%.6f")
    atomic_write_text(out / "follow_summary.json", json.dumps(summary, indent=2) + "\n")
    _plot(out / "follow.png", data, scene, summary)
    return summary


def _summary(
    d: np.ndarray,
    completed: bool,
    length: float,
    lat: list[tuple[float, float]],
    blackout_s: float,
    blind_from: float,
    inputs: str,
) -> dict[str, Any]:
    t, x, y, ct = d[:, 0], d[:, 1], d[:, 2], np.abs(d[:, 4])
    inside = np.nonzero(ct < CONVERGED_M)[0]
    conv = float(t[inside[0]]) if len(inside) else None

    def stats(sel: np.ndarray) -> dict[str, float | None]:
        v = ct[sel]
        return {
            "rms_m": float(np.sqrt(np.mean(v**2))) if len(v) else None,
            "max_m": float(v.max()) if len(v) else None,
        }

    settled = t >= max(SETTLE_S, conv if conv is not None else math.inf)
    lat_a = np.array(lat, np.float64).reshape(-1, 2)
    warm = lat_a[:, 0] < WARMUP_S  # the nodes' first frames: lazy imports and first calls
    lat_ms, warm_ms = lat_a[~warm, 1] * 1e3, lat_a[warm, 1] * 1e3
    crossing = settled & (np.hypot(x, y) < 0.5)  # the figure eight's centre
    after = stats(settled)
    out: dict[str, Any] = {
        "converged_s": conv,
        "cross_track_rms_m": after["rms_m"],
        "cross_track_max_m": after["max_m"],
        "completed": bool(completed),
        "settle_s": SETTLE_S,
        "from_converged": stats(t >= conv) if conv is not None else None,
        "crossing": stats(crossing),
        "duration_s": float(t[-1]) if len(t) else 0.0,
        "path_length_m": length,
        "measured_minus_true_cross_track_rms_m": float(
            np.sqrt(np.nanmean((d[settled, 5] - d[settled, 4]) ** 2))
        )
        if settled.any()
        else None,
        f"latency_{inputs}_to_twist_ms": {
            "n": int(len(lat_ms)),
            "p50": float(np.percentile(lat_ms, 50)) if len(lat_ms) else None,
            "p99": float(np.percentile(lat_ms, 99)) if len(lat_ms) else None,
            "max": float(lat_ms.max()) if len(lat_ms) else None,
            "warmup_s": WARMUP_S,
            "warmup_max": float(warm_ms.max()) if len(warm_ms) else None,
        },
    }
    if blackout_s > 0:
        out["blackout"] = {
            "from_s": None if math.isnan(blind_from) else blind_from,
            "s": blackout_s,
        }
    return out


def _rounded(x: Any) -> Any:
    """Floats of the summary to 0.1 mm / 0.1 ms / 1 ms: what the run can tell."""
    if isinstance(x, dict):
        return {k: _rounded(v) for k, v in x.items()}
    return round(x, 5) if isinstance(x, float) else x


def _plot(path: Path, d: np.ndarray, scene: Scene, summary: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 8), height_ratios=(3, 2))
    ref = scene.scene_T_cam[:, :2, 3]
    a.plot(ref[:, 0], ref[:, 1], "k-", lw=1, label="reference (camera)")
    fwd = SimOptions().mount.forward_m
    cam = d[:, 1:3] + fwd * np.stack([np.cos(d[:, 3]), np.sin(d[:, 3])], -1)
    a.plot(cam[:, 0], cam[:, 1], "C0-", lw=1, label="LIMO camera (true)")
    a.plot(cam[:1, 0], cam[:1, 1], "C0o")
    a.set_aspect("equal")
    a.legend(loc="upper right")
    conv, rms, mx = (summary[k] for k in ("converged_s", "cross_track_rms_m", "cross_track_max_m"))
    a.set_title(
        f"converged {conv if conv is None else round(conv, 2)} s, after {SETTLE_S:g} s: "
        f"RMS {rms if rms is None else round(rms * 100, 2)} cm, max "
        f"{mx if mx is None else round(mx * 100, 2)} cm, completed {summary['completed']}"
    )
    b.plot(d[:, 0], d[:, 4] * 100, label="true cross-track")
    b.plot(d[:, 0], d[:, 5] * 100, lw=0.8, label="measured (relocalize)")
    b.axhline(5, color="grey", ls=":")
    b.axhline(-5, color="grey", ls=":")
    b.set_xlabel("t (s)")
    b.set_ylabel("cross-track (cm, left of the path about n)")
    b.set_ylim(-40, 40)  # single-frame outliers of the measured one run off the chart
    b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)

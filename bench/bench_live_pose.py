"""Live pose quality: ``stream localize`` per frame, ``--smooth`` (the fixed-lag smoother) and the
offline joint trajectory, on the same frames of a simulated recording, against ground truth.

For each recording the node's handlers (:class:`tagtrail.stream.localize.Localizer`, the
zenoh-free part of the node) pose every frame twice — on its own and with the live smoother —
and the corners they used are solved offline by the joint model
(:func:`tagtrail.geometry.joint.solve_on_corners`: motion prior, ground-plane and
wheeled-drive decisions; once more with the recording's wheel odometry, ``odometry: auto``)
against the same fixed map (the ground truth's). The smoother is given the camera's mount
as the node is (``--camera-forward``: the simulator's). Reported: position
error RMS and max (mm), the live/offline ratio (the issue's goal: <= 1.2), the heading error's
standard deviation in the floor plane (deg; on the corridor: a straight stretch, the issue's
phi goal <= 0.3 deg) and the CPU time per frame (ms, thread time: the machine is shared).

    .venv/bin/python bench/bench_live_pose.py [--write]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tagtrail.geometry.ippe import solve_ippe  # noqa: E402
from tagtrail.geometry.joint import (  # noqa: E402
    CornerRows,
    JointSettings,
    corner_problem,
    solve_on_corners,
)
from tagtrail.geometry.joint.setup import odometry_input  # noqa: E402
from tagtrail.geometry.se3 import T_from_xyz_quat  # noqa: E402
from tagtrail.io.layouts import read_tag_map, read_trajectory  # noqa: E402
from tagtrail.io.sources import open_source  # noqa: E402
from tagtrail.schemas.documents import GroundSummary  # noqa: E402
from tagtrail.schemas.pipeline import DatasetConfig  # noqa: E402
from tagtrail.sim.simulate import simulate  # noqa: E402
from tagtrail.stages.extract import odometry_outputs  # noqa: E402
from tagtrail.stream import codec  # noqa: E402
from tagtrail.stream.continuity import (  # noqa: E402
    DeadReckoning,
    HeldGround,
    LivePoses,
    Smoother,
    SmootherSettings,
)
from tagtrail.stream.localize import Localizer  # noqa: E402
from tagtrail.stream.replay import bag_messages  # noqa: E402

CASES = [  # name, scenario, its recording, options
    ("circle, detections 0.3 px", "circle", "circle", {"frames": 300, "detections": True}),
    (
        "corridor (straight), detections 0.3 px",
        "corridor",
        "corridor",
        {"frames": 300, "detections": True},
    ),
    ("circle, rendered images", "circle", "circle", {"frames": 150, "compressed": True}),
    (
        "corridor (straight), rendered images",
        "corridor",
        "corridor",
        {"frames": 300, "compressed": True},
    ),
    ("room loop, rendered images", "room", "reference", {"frames": 600, "compressed": True}),
    ("hall out and back, rendered images", "hall", "hall", {"frames": 600, "compressed": True}),
]


NOTES = [
    "",
    "The filter's step stops once a Gauss-Newton step moves the frame less than 1 mm and "
    "1 mrad (2026-12-06: the table above; SmootherSettings.step_tol, the second step "
    "before only when that was not so): one step on 81-100 % of the frames of five "
    "seeded recordings, the poses within 31 um at p99 of two steps' (89 um at most). "
    "Rerun, every RMS within 0.003 mm of the night before; the pose's CPU p50 0.7-0.8 "
    "ms at load 0.6-1.0 (0.8-1.0 at load 1.4-2.7 before: the loads differ too much to "
    "tell the ~0.1 ms apart). Without a ground.json the room's seed 2 stays at 1.28x: "
    "its error is 1.31 mm RMS in the second second (the plane is fitted after 1 m), "
    "0.86-0.90 mm from 2 to 5 s and 0.64-0.65 mm after, against 0.57 mm over the whole "
    "run offline with the odometry: not the start alone (1.20x without its first 2 s).",
    "",
    "The odometry's read path bent (2026-12-05, late night: the table above): the "
    "odometry integrates its distance along its own heading, so a step it reads turned "
    "by more than the base turned comes out bent by half the difference "
    "(geometry/joint/odometry.py reading_model, offline and live). The corridor's seed "
    "3 draws wheels 4 % apart: 0.22 rad of yaw read per metre, and each 4 cm step "
    "straight ahead read 0.16 mm to the side (the residuals' mean against the smoothed "
    "history: -162 um a step, where the missing bend predicts -174), which the model "
    "took for the base's own motion: the lateral bias that cost that run 8 %. With the "
    "bend: its live 1.665 -> 1.464 mm, live + ground 1.492 -> 1.325, the offline solve "
    "with odometry 1.241 -> 1.240 (the batch had read it off already); over the "
    "corridor's 7 seeds live / (offline + odom) worst 1.34 -> 1.19, median 1.17 -> "
    "1.16, live + ground worst 1.20 -> 1.10; the room's (a loop, the wheels' yaw errors "
    "read in its turns) within 0.02 mm either way. With `--ground` all 14 seeded runs "
    "are now under 1.2x (worst 1.13, the room's seed 2); without it one is over (the "
    "room's seed 2, 1.28x: its first 2 s, before the plane is fitted). The six cases' "
    "load was 1.4-2.7 (a CI run beside): the CPU columns are high for it, not for the "
    "change.",
    "",
    "`live + ground` (2026-12-05 night, `stream localize --ground`, the node's default "
    "when a `ground.json` lies beside its map): the mapping run's plane and mount held "
    "from the first frame (the plane for the whole run while the history agrees with it; "
    "the mount only within 2 cm of `--camera-forward`: the mapping runs of the detections "
    "circle, the detections corridor and the rendered circle solved -0.001, 0.059 and "
    "-1.280 m, not held, their planes held), and the odometry joining the window after "
    "the first metre, held plane or not (with the plane held from the first frame it "
    "joined at once with its wheel scale and yaw errors unread: the rendered circle 0.34 "
    "-> 0.50 mm). Every case is better than `live`, the start most (the room's seed 2, "
    "first 2 s: 0.65 mm lateral and 0.81 mm height error live against 0.21 / 0.23 "
    "offline, before the plane is fitted). Over the seeds the medians are 1.09 (corridor) "
    "and 1.12 (room) against the offline solve with the odometry, the worst 1.20 (the "
    "corridor's seed 3: 1.202) and 1.14 (the room's seed 2: 1.28 -> 1.13). The `live` "
    "columns are the node without a `ground.json` beside its map: unchanged, the "
    "evening's figures to 3 digits.",
    "",
    "Each frame's pose is the filter's step (geometry/joint/newest.py): the new frame's "
    "corners and the priors' terms that reach it (taken once, at the motion's "
    "extrapolation) against the window's marginal on its two newest frames; the window is "
    "re-solved after the pose is out. For a linear problem the step is the re-solve's "
    "newest frame (tests/geometry/test_newest.py). Re-solving first instead (2026-12-04, "
    "before the level term): "
    "circle detections 2.13 mm, corridor detections 6.50, rendered circle 0.37, corridor "
    "1.55, room 0.76 (1.23x), hall 1.66: the step is within 2.5 % of it, at a fifth of the "
    "CPU before the pose is out.",
    "",
    "The smoother answers for its newest frame, which only the past constrains. Its "
    "motion prior takes the velocity in the camera's own frame (geometry/joint/motion.py, "
    "frame='camera'): a steady arc costs nothing there, where the offline world-frame "
    "form pulls the newest frame towards the straight extrapolation. Once the camera has "
    "travelled 1 m it holds the ground plane (fitted to the history, outlier poses left "
    "out), the wheeled-drive prior (the mount's yaw fitted on it, its lever arm the one "
    "given as `--camera-forward`, here the simulator's 0.084 m; dropped where the history "
    "strains it) and the wheel odometry (its unknowns held: the wheel scale and the yaw "
    "errors, turn scale, yaw per metre and drift, read against the history; no offset). "
    "Both sides hold the ground prior's level term "
    "(geometry/joint/ground.py: the height's change frame to frame, 5 mm/s/sqrt(Hz)); live "
    "only once the history's spread across its travel tells the plane's normal (a straight "
    "drive leaves it free to roll about the line: the hall's first 9 m fitted one 34 deg "
    "off, and the level term held along it put the camera 5 cm low in the U-turn). "
    "The odometry's stamps are put back on the driver's 50 Hz clock first (geometry/joint/"
    "odometry.py StampGrid: the simulator, as the LIMO, stamps each reading 2-8 ms late at "
    "publication; 1.7 ms of jitter, 0.5 on the grid), offline and live; live, the newest "
    "frame, handled before the odometry of its time arrives, gets its odometry term from the "
    "stream carried on at its last rate (Odometry.extended, up to 40 ms). From 07229d8 to "
    "the fix of geometry.ippe.map_branches (a frame of one tag took its mirrored solution 1 "
    "time in 20 in the frame-by-frame methods, which the per-frame node did not: the grid's "
    "new map showed it in tests/stream/test_live_offline.py) the grid was live only; without "
    "it offline the solve rejects the simulator's odometry on the rendered circle, corridor "
    "and hall and the room's is 0.584 mm: against that, live is room 1.18x, corridor 1.11x, "
    "hall 0.97x. "
    "`offline + odom` is the pipeline's default on these recordings (`odometry: auto`); with "
    "the stamps on the grid its strain test now takes the simulator's odometry on every one "
    "of them (before, it rejected it on the rendered circle, corridor and hall: offline hall "
    "1.80 -> 1.52 mm, circle 1.99 -> 1.58, corridor 1.30 -> 1.25). The issue's 1.2x is met "
    "on all four rendered recordings of this seed against it (room 1.19x, corridor 1.15x, "
    "hall 1.15x) and over the seeds' table (medians 1.16 and 1.17) but on 2 of the 14 "
    "seeded runs: the room's seed 2 (1.28x; live with odometry 0.74 mm, 0.82 without, the "
    "offline gains more from it) and the corridor's seed 3 (1.34x: there the odometry costs "
    "the live 8 %, a lateral bias of +0.3 mm that neither the simulator's true yaw errors nor "
    "a true mount yaw took away: the read path's missing bend, above). Before (the "
    "2026-12-05 morning's table): room 0.727 mm, "
    "1.25x, seeds median 1.23 (1.16-1.37); rendered corridor 1.61 mm. The grid alone took "
    "the room to 0.718, the newest frame's odometry term without the grid made it worse "
    "(0.735: a term off by the stamps' jitter), both 0.692. It costs the step ~0.25 ms of "
    "CPU (the odometry's terms on the new frame). The step's other priors' terms are taken "
    "ahead, with the re-solve, at the next frame's expected stamp (SmootherSettings."
    "step_ahead, the same poses to 1e-8): the pose's CPU p50 1.1-1.4 -> 0.7-1.0 ms, the "
    "re-solve's +0.3-0.6. The live odometry "
    "reads its yaw errors (turn scale, yaw per metre, drift) from the history: two wheels "
    "2-4 % apart read 0.1-0.2 rad of yaw per metre, and held at 0 that made 3 of 7 rooms "
    "1.05-1.09 mm, worse than without odometry. The level term took "
    "the room's live height spread (std) from 0.39 to 0.28 mm and the offline's from 0.25 "
    "to 0.18; what is left is mostly lateral and height jitter frame to frame (the room's "
    "seed 2: 0.18 mm of the live error above a 5-frame mean, 0.02 offline): a filter's "
    "newest frame has no later frames. Without the mount given (the lever arm "
    "fitted once the history has "
    "turned 0.5 rad, 0 until then) the rendered corridor is 1.51x, the room 2.0x (the "
    "first turn, before the fit) and the hall 1.34x. With 0.3 px corner noise it is not: "
    "the circle stays 1.64x (1.73x before the level term; mostly height and along-track: "
    "a filter's newest frame "
    "against a smoother's frames with neighbours on both sides), the corridor 1.31x "
    "(1.52x against the offline solve with the odometry). History: 2026-12-03 "
    "(world-frame motion, plane fitted to every pose, no drive, no odometry): circle "
    "detections 3.42 mm, 2.81x; corridor 11.58 mm, 2.18x, heading std 0.246 deg; rendered "
    "circle 5.22 mm, 2.61x. 2026-12-04 morning (the lever arm held at 0 until the history "
    "had turned 0.5 rad, which the weaving corridor never does): rendered corridor 1.98 "
    "mm, 1.51x, lateral 1.65 mm against 0.96 offline, heading std 0.041 deg; circle "
    "detections 2.15 mm; corridor detections 6.28 mm. The window's time budget now judges "
    "the median of the last 5 solves (a lone slow solve of a loaded machine used to halve "
    "the window: detections corridor 8.1 mm with a test run beside it). Offline keeps the "
    "world frame: with the camera frame, a stretch without tags and 1 s of wheel slip "
    "bent 26 cm (against 4.3).",
]


def _heading(R_wc: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Heading (rad) of the cameras' optical axes ``R_wc[:, :, 2]`` in the plane normal to
    ``up``."""
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    z = R_wc[:, :, 2]
    return np.arctan2(z @ b, z @ a)


def _topics(rec: Path) -> tuple[bool, list[str]]:
    image = "compressed" in (rec / "metadata.yaml").read_text()
    topics = (
        ["/camera/color/camera_info", "/camera/color/image_raw/compressed"]
        if image
        else ["/camera_info", "/detections"]
    )
    return image, topics


def _offline(rec: Path, loc: Localizer, obs: list[Any], odometry: bool) -> Any:
    """The offline joint solve of the frames' corners ``obs`` against the fixed map, with the
    recording's wheel odometry (read as extract reads it) or without."""
    frame_idx = np.concatenate([[i] * len(o[1]) for i, o in enumerate(obs)])
    t_all = np.concatenate([[o[0]] * len(o[1]) for o in obs])
    tag = np.concatenate([o[1] for o in obs])
    px = np.concatenate([o[2] for o in obs]).reshape(-1, 4, 2)
    assert loc.camera is not None
    ippe, _ = solve_ippe(px, loc.size_m[tag], loc.camera)
    st = JointSettings()
    rows = CornerRows(frame_idx, t_all, loc.ids[tag], px, loc.size_m[tag], ippe)
    pb = corner_problem(rows, tag, loc.camera, st, True)
    data = None
    if odometry:
        with open_source(DatasetConfig(source=rec)) as src:
            read = odometry_outputs(src)
        data = odometry_input(read["odometry"], read["mount"], None)
    return solve_on_corners(pb, loc.world_T_tag, np.zeros(len(loc.ids), bool), st, odometry=data)


def _mapping_ground(rec: Path) -> HeldGround:
    """``stream localize --ground``'s input from a mapping run ``rec`` (another recording of the
    scene): the plane and mount its offline joint solve with odometry held, as ``optimize``
    exports them (``ground.json``; here the cameras against the fixed map)."""
    image, topics = _topics(rec)
    m = bag_messages(rec, topics)
    loc = Localizer(read_tag_map(rec / "ground_truth" / "tag_map.yaml")[0])
    obs = []
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k.endswith("camera_info"):
            loc.on_camera_info(p)
            continue
        try:
            single = loc.on_image(p) if image else loc.on_detections(p)
        except Exception:  # noqa: BLE001 - no pose for this frame
            continue
        q = codec.decode_pose(single[0][1])
        assert loc._last_obs is not None
        obs.append((q.sec * 10**9 + q.nanosec, *loc._last_obs))
    sol = _offline(rec, loc, obs, odometry=True)
    doc = GroundSummary.model_validate(dataclasses.asdict(sol.ground)).known()
    assert doc is not None, "the mapping run's solve held no ground plane"
    return HeldGround.of(doc)


def _case(rec: Path, held: HeldGround | None = None) -> dict[str, Any]:
    gt = read_trajectory(rec / "ground_truth" / "trajectory.csv").set_index("t_ns")
    tags = read_tag_map(rec / "ground_truth" / "tag_map.yaml")[0]
    image, topics = _topics(rec)
    m = bag_messages(rec, [*topics, "/odom"])  # the simulator's wheel odometry
    loc = Localizer(tags)
    # the camera's mount, as `--camera-forward` (or `--profile limo`) gives it to the node
    scene = yaml.safe_load((rec / "ground_truth" / "scene.yaml").read_text())
    forward = float(scene["options"]["mount"]["forward_m"])

    def smoother(ground: HeldGround | None = None) -> LivePoses:
        return LivePoses(
            Smoother(loc.world_T_tag, loc.size_m, SmootherSettings(lever_m=forward, ground=ground)),
            DeadReckoning(camera_forward_m=forward),
            "tag_only_pose",
            "localize",
            "map",
        )

    live, blind = smoother(), smoother()  # with the odometry (--odom-key), without
    # with the odometry and the mapping run's plane and mount (--ground)
    mapped = smoother(held) if held is not None else None
    got: dict[str, list[Any]] = {"frame": [], "live": [], "no_odom": []}
    if mapped is not None:
        got["ground"] = []
    obs, cpu = [], []
    for k, p in zip(m.keys, m.payloads, strict=True):
        if k.endswith("camera_info"):
            loc.on_camera_info(p)
            continue
        if k.endswith("odom"):
            live.on_odometry(p)
            if mapped is not None:
                mapped.on_odometry(p)
            continue
        loc.live = None
        try:
            single = loc.on_image(p) if image else loc.on_detections(p)
        except Exception:  # noqa: BLE001 - no pose for this frame (counted by the node)
            continue
        assert loc._last_obs is not None
        q = codec.decode_pose(single[0][1])
        t_ns = q.sec * 10**9 + q.nanosec
        obs.append((t_ns, *loc._last_obs))
        loc.smooth(live)
        own = T_from_xyz_quat(np.array([q.x, q.y, q.z]), np.array([q.qx, q.qy, q.qz, q.qw]))
        t0 = time.thread_time()
        out = live.on_frame(t_ns, own, loc._last_obs, loc.camera)  # as the node's --smooth
        t1 = time.thread_time()
        live.settle()  # as the node, once the pose is out: the window's re-solve
        cpu.append((t1 - t0, time.thread_time() - t1))
        got["frame"].append(single[0][1])
        got["live"].append(dict(out)["tag_only_pose"])
        no = blind.on_frame(t_ns, own, loc._last_obs, loc.camera)
        blind.settle()
        got["no_odom"].append(dict(no)["tag_only_pose"])
        if mapped is not None:
            on = mapped.on_frame(t_ns, own, loc._last_obs, loc.camera)
            mapped.settle()
            got["ground"].append(dict(on)["tag_only_pose"])
    sol = _offline(rec, loc, obs, odometry=False)
    pb = sol.pb
    R_off = np.swapaxes(sol.res.R_cam, 1, 2)
    c_off = -np.einsum("fij,fj->fi", R_off, sol.res.t_cam)
    # the same with the recording's wheel odometry, read as extract reads it (variances, the
    # /tf_static mount): the pipeline's default when a bag has it
    sol_o = _offline(rec, loc, obs, odometry=True)
    assert len(sol_o.pb.t_ns) == len(pb.t_ns)  # every frame has a tag: the same frames
    c_odo = -np.einsum("fji,fj->fi", sol_o.res.R_cam, sol_o.res.t_cam)
    cols = ["x_m", "y_m", "z_m"]
    g = gt.loc[pb.t_ns]
    G = T_from_xyz_quat(g[cols].to_numpy(), g[["qx", "qy", "qz", "qw"]].to_numpy())
    up = -np.mean(G[:, :3, 1], axis=0)  # the camera's y points down
    up /= np.linalg.norm(up)
    h_true = _heading(G[:, :3, :3], up)
    out: dict[str, Any] = {}
    for name, payloads in got.items():
        P = np.array([[*codec.decode_pose(b)[3:]] for b in payloads])
        T = T_from_xyz_quat(P[:, :3], P[:, 3:])
        e = np.linalg.norm(T[:, :3, 3] - G[:, :3, 3], axis=1)
        dh = np.angle(np.exp(1j * (_heading(T[:, :3, :3], up) - h_true)))
        out[name] = (e, dh)
    e_off = np.linalg.norm(c_off - G[:, :3, 3], axis=1)
    dh_off = np.angle(np.exp(1j * (_heading(R_off, up) - h_true)))
    out["offline"] = (e_off, dh_off)
    R_odo = np.swapaxes(sol_o.res.R_cam, 1, 2)
    dh_odo = np.angle(np.exp(1j * (_heading(R_odo, up) - h_true)))
    out["offline_odom"] = (np.linalg.norm(c_odo - G[:, :3, 3], axis=1), dh_odo)
    row: dict[str, Any] = {"frames": len(obs)}
    for name, (e, dh) in out.items():
        row[name] = {
            "rms_mm": float(np.sqrt(np.mean(e**2)) * 1e3),
            "max_mm": float(e.max() * 1e3),
            "heading_std_deg": float(np.degrees(np.std(dh))),
        }
    row["live_over_offline"] = row["live"]["rms_mm"] / row["offline"]["rms_mm"]
    row["live_over_offline_odom"] = row["live"]["rms_mm"] / row["offline_odom"]["rms_mm"]
    if "ground" in row:
        row["ground_over_offline_odom"] = row["ground"]["rms_mm"] / row["offline_odom"]["rms_mm"]
    row["offline_odometry_used"] = sol_o.odometry_part is not None
    c = np.array(cpu) * 1e3
    for j, part in enumerate(("pose", "settle")):  # the pose out, then the window's re-solve
        row[f"live_{part}_cpu_ms_p50"], row[f"live_{part}_cpu_ms_p99"] = (
            float(np.percentile(c[:, j], 50)),
            float(np.percentile(c[:, j], 99)),
        )
    return row


# The 1.2x over the simulator's draws: each seed draws the wheels' scale errors (1-3 %, either
# sign), the gyro's drift and the corners' noise; the table's seed (5) is one of them.
SEEDED = [(name, scen, rec, opts) for name, scen, rec, opts in CASES if "rendered" in name]
SEEDED = [c for c in SEEDED if c[1] in ("room", "corridor")]


def _mapping_run(scen: str, rec: str, opts: dict[str, Any], out: Path, seed: int) -> Path:
    """The mapping run of a case: the same scene and drive recorded again, another draw of the
    simulator's errors (seed + 100)."""
    return simulate(scen, out, corner_noise_px=0.3, seed=seed + 100, **opts)[rec]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--write", action="store_true")
    ap.add_argument(
        "--seeds",
        type=int,
        default=7,
        help="the rendered room's loop and corridor over simulator seeds 1..N (0: not)",
    )
    a = ap.parse_args()
    rows, seeded = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, scen, rec, opts) in enumerate(CASES):
            recs = simulate(scen, Path(tmp) / str(i), corner_noise_px=0.3, seed=5, **opts)
            held = _mapping_ground(_mapping_run(scen, rec, opts, Path(tmp) / f"m{i}", 5))
            row = {"case": name, **_case(recs[rec], held), "load": os.getloadavg()[0]}
            print(json.dumps(row), flush=True)
            rows.append(row)
        for name, scen, rec, opts in SEEDED:
            for seed in range(1, a.seeds + 1):
                out = Path(tmp) / f"{scen}-{seed}"
                recs = simulate(scen, out, corner_noise_px=0.3, seed=seed, **opts)
                held = _mapping_ground(
                    _mapping_run(scen, rec, opts, Path(tmp) / f"m-{scen}-{seed}", seed)
                )
                r = _case(recs[rec], held)
                row = {
                    "case": name,
                    "seed": seed,
                    **{
                        k: r[k]["rms_mm"]
                        for k in ("live", "no_odom", "offline", "offline_odom", "ground")
                    },
                    "over": r["live_over_offline"],
                    "over_odom": r["live_over_offline_odom"],
                    "ground_over_odom": r["ground_over_offline_odom"],
                }
                print(json.dumps(row), flush=True)
                seeded.append(row)
    if a.write:
        _write(rows, seeded)


def _write(rows: list[dict[str, Any]], seeded: list[dict[str, Any]]) -> None:
    lines = [
        "# Live pose quality (bench/bench_live_pose.py)",
        "",
        f"{dt.date.today()}, load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores. "
        "`stream localize`'s handlers on every frame of a simulated recording: each frame on "
        "its own (`frame`), `--smooth --odom-key odom` (the fixed-lag smoother, 2 s / 60 "
        "frames, 2 iterations, with the recording's wheel odometry; `live`), the same with "
        "the mapping run's ground plane and mount held from the first frame (`--ground`, "
        "`live + ground`: the plane and mount the offline joint solve with odometry held on "
        "another recording of the same scene and drive, simulator seed + 100, as optimize "
        "exports them in ground.json), the same without the odometry or the ground "
        "(`no odom`) and the offline joint solve of the same corners against the "
        "same fixed map (`offline`, no odometry; `offline + odom`: with the recording's "
        "odometry, `odometry: auto`, the pipeline's default). Error = camera position vs "
        "ground truth; heading = the optical axis in the floor plane, its error's standard "
        "deviation (on the corridor: a straight drive, phi's spread there). CPU = the "
        "smoother's thread time per frame (`live`): the pose (the filter's step) / the "
        "window's re-solve after it (the per-frame pose comes on top, ~1 ms).",
        "",
        "| case | frames | frame RMS / max mm | live RMS / max mm | "
        "live + ground RMS / max mm | no odom RMS / max mm | "
        "offline RMS / max mm | offline + odom RMS / max mm (applied) | "
        "live / offline (/ + odom) | live + ground / (offline + odom) | "
        "heading std deg frame / live / offline | "
        "live CPU ms p50 / p99: pose, re-solve | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        f, li, no, o, oo = r["frame"], r["live"], r["no_odom"], r["offline"], r["offline_odom"]
        gr = r["ground"]
        used = "yes" if r["offline_odometry_used"] else "no"
        lines.append(
            f"| {r['case']} | {r['frames']} | {f['rms_mm']:.2f} / {f['max_mm']:.1f} | "
            f"{li['rms_mm']:.2f} / {li['max_mm']:.1f} | {gr['rms_mm']:.2f} / {gr['max_mm']:.1f} | "
            f"{no['rms_mm']:.2f} / {no['max_mm']:.1f} | "
            f"{o['rms_mm']:.2f} / {o['max_mm']:.1f} | "
            f"{oo['rms_mm']:.2f} / {oo['max_mm']:.1f} ({used}) | "
            f"{r['live_over_offline']:.2f} / {r['live_over_offline_odom']:.2f} | "
            f"{r['ground_over_offline_odom']:.2f} | "
            f"{f['heading_std_deg']:.3f} / "
            f"{li['heading_std_deg']:.3f} / {o['heading_std_deg']:.3f} | "
            f"{r['live_pose_cpu_ms_p50']:.1f} / {r['live_pose_cpu_ms_p99']:.1f}, "
            f"{r['live_settle_cpu_ms_p50']:.1f} / {r['live_settle_cpu_ms_p99']:.1f} | "
            f"{r['load']:.1f} |"
        )
    if seeded:
        lines += [
            "",
            "Over the simulator's seeds (each draws the wheels' scale errors, 1-3 %, either "
            "sign, the gyro's drift and the corners' noise), RMS mm; the median of the ratios "
            "last:",
            "",
            "| case | seed | live | live + ground | no odom | offline | offline + odom | "
            "live / offline | live / (offline + odom) | live + ground / (offline + odom) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for name in dict.fromkeys(r["case"] for r in seeded):
            rs = [r for r in seeded if r["case"] == name]
            for r in rs:
                lines.append(
                    f"| {name} | {r['seed']} | {r['live']:.3f} | {r['ground']:.3f} | "
                    f"{r['no_odom']:.3f} | {r['offline']:.3f} | {r['offline_odom']:.3f} | "
                    f"{r['over']:.2f} | {r['over_odom']:.2f} | {r['ground_over_odom']:.2f} |"
                )
            keys = ("over", "over_odom", "ground_over_odom")
            med = [float(np.median([r[k] for r in rs])) for k in keys]
            top = [max(r[k] for r in rs) for k in keys]
            lines.append(
                f"| {name} | median of {len(rs)} (max) | | | | | | **{med[0]:.2f}** "
                f"({top[0]:.2f}) | **{med[1]:.2f}** ({top[1]:.2f}) | **{med[2]:.2f}** "
                f"({top[2]:.2f}) |"
            )
    lines += NOTES
    (ROOT / "bench" / "LIVE_POSE.md").write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

"""The closed loop of ``tagtrail simulate follow``: tracking and latency, with and without a tag
blackout.

Runs :func:`tagtrail.sim.follow.run` (simulated LIMO + ``stream localize`` → ``relocalize`` →
``follow`` processes over zenoh on 127.0.0.1, real time) from 0.3 m and 30° off the figure
eight at 0.3 m/s; the same with rendered 640x480 images instead of detections, and with
``--blackout 2`` (no tag in view for 2 s from mid-path): each case with ``stream localize``
posing frames on their own (the follower stops after 0.5 s of blackout and waits) and with
``--smooth`` on the LIMO's odometry (dead reckoning bridges it). Latency = the simulator
publishes a frame's detections (or image) → the first Twist back on ``cmd_vel``, one clock
(three hops: localize, relocalize, follow). Prints one JSON line per case; ``--write`` puts
the table into ``bench/FOLLOW.md``.

    .venv/bin/python bench/bench_follow.py [--seeds 0 1] [--write]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tagtrail.sim.follow import run  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--blackout", type=float, nargs="+", default=[0.0, 2.0])
    ap.add_argument("--no-images", action="store_true", help="skip the rendered-images case")
    ap.add_argument(
        "--smooth",
        choices=["off", "on", "both"],
        default="both",
        help="stream localize --smooth with the LIMO's odometry (default: both)",
    )
    ap.add_argument(
        "--low-latency",
        choices=["off", "on", "both"],
        default="on",
        help="the nodes' links on zenoh's low-latency transport (simulate follow's default: on)",
    )
    ap.add_argument("--write", action="store_true")
    a = ap.parse_args()
    rows = []
    smooths = {"off": [False], "on": [True], "both": [False, True]}[a.smooth]
    fasts = {"off": [False], "on": [True], "both": [False, True]}[a.low_latency]
    cases = [(b, False, sm) for sm in smooths for b in a.blackout]
    cases += [] if a.no_images else [(0.0, True, sm) for sm in smooths]
    for blackout, images, smooth in cases:
        # seeds outside, transports inside: a pair of runs side by side on the same host state
        for seed, fast in ((s, f) for s in a.seeds for f in fasts):
            with tempfile.TemporaryDirectory() as tmp:
                s = run(
                    Path(tmp),
                    blackout_s=blackout,
                    seed=seed,
                    images=images,
                    smooth=smooth,
                    low_latency=fast,
                )
            inputs = "images" if images else "detections"
            lat = s[f"latency_{inputs}_to_twist_ms"]
            skipped = s["nodes"]["localize"]["stats"]["dropped"].get("skipped", 0)
            row = {
                "input": inputs,
                "smooth": smooth,
                "low_latency": fast,
                "load": os.getloadavg()[0],
                "skipped": skipped,
                "blackout_s": blackout,
                "seed": seed,
                "converged_s": s["converged_s"],
                "rms_cm": s["cross_track_rms_m"] * 100,
                "max_cm": s["cross_track_max_m"] * 100,
                "crossing_max_cm": s["crossing"]["max_m"] * 100,
                "completed": s["completed"],
                "duration_s": s["duration_s"],
                "lat_p50_ms": lat["p50"],
                "lat_p99_ms": lat["p99"],
                "lat_n": lat["n"],
            }
            print(json.dumps(row), flush=True)
            rows.append(row)
    if a.write:
        _write(rows, os.getloadavg()[0])


def _write(rows: list[dict[str, Any]], load: float) -> None:
    lines = [
        "# Closed-loop following (bench/bench_follow.py)",
        "",
        f"{dt.date.today()}, load {load:.1f} on {os.cpu_count()} cores. Figure eight "
        "(9.08 m, self-crossing), start 0.3 m / 30 deg off, 0.3 m/s, Stanley, LIMO "
        "profile; detections with 0.3 px corner noise. Cross-track = true (ground truth) "
        "after 5 s; latency = detections (or a rendered 640x480 rgb8 image) published -> "
        "Twist received (3 node hops: localize, relocalize, follow). Images: localize "
        "detects the tags, re-fits their corners by the gradient alone (--refit-corners "
        "edges: the intensity-profile model would add ~3 ms a tag) and skips frames that "
        "arrive while it is busy. Issue 28's targets: images p99 <= 33 ms and detections "
        "p99 <= 5 ms. Per frame a node's every message costs 2-3x its time in a loop "
        "(caches gone cold while it waits 33 ms; measured: a CameraInfo 60 us in a loop, "
        "350 us with 33 ms sleeps between; a dead-reckoned pose 32 us run twice in a "
        "row, 120-215 us after a 20 ms sleep on an otherwise idle machine, spinning the "
        "CPU before it did not help: the host's other tenants take the caches), so latency "
        "is counted in Python calls: a "
        "CameraInfo that only differs in its stamp is not parsed again, a frame posed by "
        "multi-tag PnP builds no per-tag IPPE pose, a pose's quaternion skips scipy. Every "
        "node (and the simulator) collects Python's garbage between messages, not in them "
        "(stream/node.py: automatic, a young generation's collection took ~1 ms some 25 "
        "times in 30 s, in each node). A sample that finds a node idle is handled on "
        "zenoh's delivering thread (handing it to a worker cost ~60 us a hop at p50, "
        "0.7-1.9 ms at p99), and a node's work after a message (localize's hand-over of "
        "its window's re-solve, the garbage) runs 2 ms after it, so the nodes downstream "
        "have both cores first (--smooth p99 median 7.9 -> 7.0 ms in 6 alternated runs on "
        "a loaded hour, better in all 6); a message still being handled then puts it off "
        "until 2 ms after its own outputs (at most 6 ms): a frame comes right after its "
        "CameraInfo, and until 2026-12-05 that ran the hand-over straight after every "
        "frame's outputs (localize's pose -> Twist p99 2.5-3.3 -> 1.5 ms, detections -> "
        "Twist 5.5-7.4 -> 4.4-5.5 ms in 3 alternated traced pairs). With --smooth each "
        "frame's "
        "pose leaves after the "
        "filter's step (~1 ms of CPU: its corners and, taken once from the motion's "
        "extrapolation, the priors' terms against the window's marginal) and the window "
        "is re-solved after (~7 ms) in a child process at SCHED_IDLE "
        "(stream/background.py; on a thread niced +10 it shared the GIL with the handlers "
        "and Linux's EEVDF scheduler let it finish its slice before relocalize and follow "
        "ran: hops of 2-4 ms at p90), whose result is taken between messages (the node "
        "asks every 2 ms while it is out; left to an odometry message's after-work, a "
        "fifth of the frames took it first, ~0.2 ms) instead of before the next frame's "
        "step. Detections, "
        "per frame: p99 3.0-4.2 ms in today's 6 bench runs (3.3-4.4 the day before). "
        "--smooth, as below (the odometry's scales read again off the step's path, its "
        "prior left out of the step while it cannot reach the new frame): p50 2.0-3.1, "
        "p99 3.5-6.2 in 6 cases of 3 runs (median 4.2; 5 under 5 ms, the one over at "
        "p50 3.1, a slow spell); 4.5-5.7 (median 4.8) in the 8 before those two changes "
        "(4.2 and 5.5 with the first only), "
        "4.1-6.4 in the 8 before the result was asked for every 2 ms (the hand-over put "
        "off only), 5.1-5.4 the day before (the hand-over after every frame's outputs), "
        "6.4-8.9 two days before. With the ground prior's level term in the step "
        "(+35 us cold) and the live odometry's yaw fit (the table below): 3.3 and 5.0 "
        "here; the day's 7 runs with the level term 3.3-5.3, median 4.5, 6 under 5 ms (5.3 "
        "at load 1.1 straight after a benchmark, its p50 3.0); per frame 3.4 and 2.8. "
        "What is left is the step's ~0.8 ms of CPU (2x that "
        "cold) and the machine: the same code's --smooth p99 ran from 4.2 to 8.5 ms over "
        "a day's experiments, so changes were judged in runs alternated with the code "
        "before, or by the work they take off a frame's path (traced). Images: localize "
        "skipped 2-15 frames while busy and the loop converged in 2.1-2.5 s over today's "
        "runs (the code before as well, in runs alternated with it: the machine's "
        "state). Latency counts "
        "the frames with a tag in view (a Twist after a blind frame is the follower's "
        "stop: counted, it made the 2 s blackout's p99 ~21 ms) from 1 s on; the first "
        "second's worst (the nodes' warm-up) is 20-70 ms.",
        "",
        "2026-12-05 afternoon, three seeds a case (the host slower than in the morning: "
        "per frame p50 2.6-3.5 where it was 1.9-2.6). The dead reckoning now takes the "
        "odometry's errors the smoother read off each step (DeadReckoning.errors): the 2 s "
        "blackout's max 0.88 / 4.82 / 5.29 cm over seeds 0-2 -> 0.36 / 0.31 / 0.36 (seeds "
        "1 and 2 draw wheels 2-4 % apart; the morning's table had seed 0 only). The "
        "step's priors' terms but the odometry's are taken ahead, once the window is "
        "re-solved (SmootherSettings.step_ahead): traced, localize's detections -> pose "
        "p50 3.15 -> 2.27 ms, p99 5.0 -> 4.0; the step also gained the odometry's term on "
        "the new frame (+0.25 ms CPU, bench/LIVE_POSE.md). --smooth detections -> Twist "
        "p99 4.9 / 5.3 / 4.9, blackout 5.2 / 6.2 / 5.5 (before the step ahead, the same "
        "afternoon: 6.1 / 5.8 / 5.6 and 6.2 / 4.7 / 5.7; with neither, 5.0 / 5.8 / 5.4 "
        "and 6.2 / 5.9 / 5.1); per frame 3.5-4.4. What is left of the tail is past "
        "localize: pose -> Twist through relocalize and follow, and the host.",
        "",
        "2026-12-05 evening (the table below; the map_branches fix, the offline stamp grid, "
        "the step ahead's give-up; nothing on the live path of these runs changed): a host "
        "~1.4x slower again (bench/LIVE_POSE.md: the same re-solve 10.5-11 ms p50 against "
        "7.5), per frame p99 4.6-5.0 (3.5-4.4 in the afternoon), --smooth 5.8 / 6.5 / 8.5, "
        "blackout 6.4 / 6.1 / 6.2, images 20-26 (the 33 ms target met). Tracking as before "
        "in every run: converged 2.0-2.1 s (images 2.4-2.6), max 0.30-0.46 cm, all "
        "completed. Node processing on a --smooth run: localize p50 0.55-0.68 ms, p99 "
        "4.9-5.6 (frames and odometry messages), relocalize 0.32-0.38 / 0.8-1.0, follow "
        "0.15-0.19 / 0.37-0.51. Leaving the dead-reckoned poses between frames out (77 "
        "poses a second through relocalize and follow -> 30) did not shorten the tail "
        "(p99 7.5 / 7.0 with them, 8.1 / 7.2 without, alternated): the tail is localize's "
        "step on a slow host, not the extra traffic.",
        "",
        "2026-12-05 late (the table below), on the evening's slow host. (1) The simulator's "
        "sensors on their own clocks (docs/FOLLOW.md): the camera exposes at 30 Hz and "
        "stamps each frame with its exposure, the wheels are read at 50 Hz (stamped at "
        "publication, 2-8 ms later, as before). Before, a frame was rendered and stamped at "
        "the loop's 4 ms tick, an exposure clock jittering by up to 4 ms that no camera "
        "has: the smoother's step was never taken ahead (the priors' terms, ~0.6 ms "
        "cold, computed on each frame's arrival), and the wheel readings lay off the 50 Hz "
        "grid the node's stamp grid puts them on. With exposure stamps a frame arrives "
        "behind odometry of later stamps, and its pose was dropped (poses leave in stamp "
        "order; the first run showed a p99 of 18 ms): now its fix is carried to the newest "
        "pose's stamp (docs/LIVE.md). (2) The step's odometry term from its closed-form "
        "model and a scalar reading instead of the window's prior over 3 frames. Traced "
        "(one run each): localize's detections handler p50 2.9 -> 1.8-2.0 ms, p99 5.0 -> "
        "3.0-3.3. 18 runs with (1) and (2): per frame p99 4.2-4.6, --smooth 5.7 / 5.7 / "
        "5.8, blackout 6.2 / 5.5 / 5.7, images 20-25. (3) While a frame is in flight the "
        "simulator stays off the CPU until its Twist (at most 10 ms) and hands the "
        "interpreter's lock over every 0.5 ms: its own Python work (the next steps, the "
        "truth's tracker) took a core from the nodes on 2 cores and delayed the Twist's "
        "callback (follow's start -> Twist received, worst 3 %: 1.83 -> 0.88 ms); a step "
        "caught up after a command takes the command in force at its time. "
        "With all three: per frame p99 4.2-4.7 ms (6 of 6 under 5), --smooth 5.5 / 5.0 / "
        "4.8, blackout 6.5 / 4.4 / 5.2, images 22.7-26.8 (p50 15.4-16.5: past its 10 ms the "
        "pause spun until the Twist, a core taken from localize's detection; now the loop "
        "takes its steps again). The table, with that fixed: per frame p99 4.0-4.7 ms (6 "
        "of 6 under 5), --smooth 5.2 / 5.1 / 4.8, blackout 4.9 / 5.2 / 5.3 (2 of 6 under 5, "
        "the rest 5.1-5.3), images 18.1-20.1 (p50 13.8-15.0); tracking as before "
        "(converged 2.0-2.15 s, max <= 0.51 cm, all completed). A camera stamped by a "
        "jittery host clock (stamps off their "
        "period by more than 2 us) takes the step on arrival: about the evening's "
        "figures.",
        "",
        "2026-12-05 night (the table below, side by side: each seed run with the nodes' "
        "links on zenoh's ordinary transport, then on its low-latency one, "
        "`--low-latency`, simulate follow's default now; a loaded host, load 0.4 on the "
        "per-frame rows, 1.1-2.0 on the rest). The low-latency transport writes a "
        "sample to the socket from the publishing thread instead of handing it to "
        "zenoh's transmit task. Detections, per frame: p50 median 3.53 -> 3.14 ms, p99 "
        "4.86 -> 4.62 (5 of 6 under 5 ms, 4 of 6 before). --smooth: p50 3.47 -> 3.32, "
        "p99 5.59 -> 5.54 (1 of 6 under 5, 0 before; one ordinary run 13.2, a stall); "
        "in 7 alternated pairs of one --smooth run each just before, at load 0.3-1.0: "
        "p99 median 5.48 -> 5.03, better in 6 of 7. Images: no change (their link is "
        "never low-latency: zenoh's does not fragment, and measured here the first "
        "sample over 64 KiB on such a link was lost). Tracking unchanged: converged "
        "2.0-2.2 s, max <= 0.49 cm, all completed. The --smooth target (p99 <= 5 ms) is "
        "met on a quiet host only: the p99 moves by +-0.7 ms run to run and by more "
        "with the host's other tenants.",
        "",
        "2026-12-06 (the table below). The simulator puts a frame's detections a step "
        "(~4 ms) after its camera_info, as a detector's output follows the camera driver's "
        "message (apriltag_ros takes longer): put at once after it, the CameraInfo's "
        "handling (~0.1 ms warm, 0.35 cold) lay on every frame's path, and in 4 alternated "
        "pairs of --smooth runs the p99 went 4.75-5.63 -> 3.85-4.42 ms, p50 -0.5. Also: "
        "relocalize publishes the state first (what follow steers by), and the live "
        "smoother's step stops after one Gauss-Newton step when it moves the frame less "
        "than 1 mm and 1 mrad (bench/LIVE_POSE.md). The host ran 30-40 % slower than in "
        "the morning by the afternoon (the same in-process step: 1.12 -> 1.44 ms p50), "
        "so the morning's runs of the code before (per frame p99 4.0-4.6, --smooth "
        "4.8-5.5) are not the table's baseline. Here: per frame p99 3.8-4.3 ms (6 of 6 "
        "under 5), --smooth 4.1-5.6 (median 4.5; 5 of 6 under 5, the one over at load "
        "1.3), images 21-22 (33 ms target met). Tracking as before: converged 2.0-2.2 s, "
        "max <= 0.48 cm, all completed.",
        "",
        "`smooth`: `stream localize --smooth --odom-key odom` (the fixed-lag smoother and "
        "dead reckoning on the LIMO's odometry: it bridges the blackout); without it each "
        "frame is posed on its own and the follower stops in the blackout. Load: the "
        "1-minute load average when the row finished (2 cores shared by 5 engineers: "
        "latencies are pessimistic).",
        "",
        "| input | smooth | low latency | blackout s | seed | converged s | RMS cm | max cm | "
        "crossing max cm | completed | duration s | latency p50 ms | p99 ms | "
        "frames skipped by localize | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['input']} | {'on' if r['smooth'] else 'off'} | "
            f"{'on' if r['low_latency'] else 'off'} | {r['blackout_s']:g} | "
            f"{r['seed']} | "
            f"{r['converged_s']:.2f} | "
            f"{r['rms_cm']:.2f} | {r['max_cm']:.2f} | {r['crossing_max_cm']:.2f} | "
            f"{r['completed']} | {r['duration_s']:.1f} | {r['lat_p50_ms']:.1f} | "
            f"{r['lat_p99_ms']:.1f} | {r['skipped']} | {r['load']:.1f} |"
        )
    (ROOT / "bench" / "FOLLOW.md").write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

"""``tagtrail simulate follow``: the closed loop (simulated LIMO, stream localize → relocalize →
follow as processes over zenoh on 127.0.0.1) from 0.3 m and 30° off the figure eight at
0.3 m/s; plus the simulated LIMO's kinematics and odometry error model."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tagtrail.cli import main
from tagtrail.sim import limo
from tagtrail.sim.follow import COLUMNS, eight_poly
from tagtrail.stream import codec
from tests.sim.helpers import detector, image_of

pytestmark = pytest.mark.slow  # closed-loop simulations (make test-all)


def test_kinematics_obey_the_limos_limits() -> None:
    k = limo.Kinematics()
    k.command(3.0, 10.0, 0.0)
    for i in range(200):
        k.step(i * 0.01, 0.01)
    assert k.v <= limo.MAX_SPEED_MPS + 1e-12
    assert abs(k.omega) <= k.v / limo.MIN_TURN_RADIUS_M + 1e-12
    # circle of the minimum radius: its centre stays put
    r = np.hypot(k.x - 0.0, k.y - limo.MIN_TURN_RADIUS_M)
    assert abs(r - limo.MIN_TURN_RADIUS_M) < 0.03
    k.step(10.0, 0.01)  # no command for > 0.5 s: the base stops on its own
    for i in range(100):
        k.step(10.0 + i * 0.01, 0.01)
    assert abs(k.v) < 1e-3


def test_steps_caught_up_after_a_command_take_the_one_in_force_at_their_time() -> None:
    """The simulator integrates lazily (after a frame's Twist, or its 4 ms tick): a command
    that came at t = 0.4 s moves the base only from then on, not over the steps before it."""
    late, timely = limo.Kinematics(), limo.Kinematics()
    for k in (late, timely):
        k.command(0.3, 0.0, 0.0)
    for i in range(40):  # to 0.4 s under the first command
        timely.step(i * 0.01, 0.01)
    late.command(0.0, 0.0, 0.4)  # the stop came before the steps to 0.4 s were taken
    timely.command(0.0, 0.0, 0.4)
    for i in range(40):
        late.step(i * 0.01, 0.01)
    assert late.x == timely.x and late.v == timely.v > 0.29
    late.step(0.4, 0.01)
    assert late.v < timely.v  # from 0.4 s the stop


def test_odometry_error_model() -> None:
    for seed in range(20):
        odo = limo.WheelOdometry(np.random.default_rng(seed))
        sl, sr = odo.scale_l, odo.scale_r
        assert 0.01 <= abs(sl - 1) <= 0.03 and 0.01 <= abs(sr - 1) <= 0.03
        assert abs(odo.drift_rps) <= math.radians(0.3)
        odo.step(1.0, 0.0, 0.01)  # straight: distance off by the mean scale, yaw drifts
        assert math.isclose(odo.v, (sl + sr) / 2)
        assert math.isclose(odo.omega, (sr - sl) / limo.TRACK_M + odo.drift_rps)
        odo.step(0.5, 1.0, 0.01)  # a turn: slip over-reads the yaw rate
        wheels = (0.5 + limo.TRACK_M / 2) * sr - (0.5 - limo.TRACK_M / 2) * sl
        assert odo.omega - odo.drift_rps > wheels / limo.TRACK_M
    stamp = 1_700_000_000_123_456_789
    assert tuple(codec.decode_pose(odo.message(stamp), "odometry")[:2]) == divmod(stamp, 10**9)


def test_figure_eight_crosses_itself() -> None:
    xy = eight_poly()
    mid = np.hypot(*xy.T) < 0.05
    assert mid.any() and np.hypot(*(xy[0] - xy[-1])) > 0.3  # an open path with an end


def test_closed_loop_figure_eight(tmp_path: Path, capsys: object) -> None:
    out = tmp_path / "eight"
    assert (
        main(
            [
                "simulate",
                "follow",
                "--out",
                str(out),
                "--start-offset",
                "0.3",
                "--start-heading",
                "30",
                "--speed",
                "0.3",
            ]
        )
        == 0
    )
    s = json.loads((out / "follow_summary.json").read_text())
    print(
        json.dumps(
            {
                k: s[k]
                for k in (
                    "converged_s",
                    "cross_track_rms_m",
                    "cross_track_max_m",
                    "crossing",
                    "latency_detections_to_twist_ms",
                )
            }
        )
    )
    assert (out / "follow.csv").read_text().splitlines()[0] == COLUMNS
    assert (out / "follow.png").stat().st_size > 0
    assert (out / "ground_truth" / "trajectory.csv").is_file()
    assert (out / "ground_truth" / "tag_map.yaml").is_file()
    # the targets
    assert s["completed"]
    assert s["converged_s"] is not None and s["converged_s"] <= 5.0
    assert s["cross_track_rms_m"] <= 0.02
    assert s["cross_track_max_m"] <= 0.05
    assert s["crossing"]["max_m"] <= 0.05
    for name, node in s["nodes"].items():
        assert node["exit"] == 0 and node["stats"]["shutdown_clean"], name


def test_rendered_frames_show_the_tags_and_blind_ones_none() -> None:
    from tagtrail.sim.follow import eight_scene
    from tagtrail.sim.render import Renderer
    from tagtrail.sim.scenarios import SimOptions

    scene = eight_scene(SimOptions())
    rng = np.random.default_rng(0)
    renderer = Renderer(scene, SimOptions().realism, seed=0)
    det = detector()
    for blind in (False, True):
        data, info = limo.image(renderer, scene, scene.scene_T_cam[0], 123, rng, blind)
        msg = codec.deserialize(data, "sensor_msgs/msg/Image")
        assert (msg.width, msg.height, msg.encoding) == (640, 480, "rgb8")
        gray = image_of(msg).mean(axis=2).astype(np.uint8)
        found = {d.tag_id for d in det.detect(gray)}
        _, _, n = limo.detections(scene, scene.scene_T_cam[0], 123, SimOptions(), rng, blind)
        assert len(found) == n and (n == 0) == blind
        assert codec.deserialize(info, "sensor_msgs/msg/CameraInfo").width == 640


def test_closed_loop_blackout_stops_then_resumes(tmp_path: Path) -> None:
    """2 s without a tag from mid-path: no pose (localize has no odometry yet), the follower
    commands zero within 0.5 s (+ one frame and the hops), waits, resumes and completes."""
    out = tmp_path / "blackout"
    assert main(["simulate", "follow", "--out", str(out), "--blackout", "2", "--seed", "1"]) == 0
    s = json.loads((out / "follow_summary.json").read_text())
    t0 = s["blackout"]["from_s"]
    d = np.loadtxt(out / "follow.csv", delimiter=",", skiprows=1)
    t, v_cmd = d[:, 0], d[:, 8]
    assert (v_cmd[(t > t0 - 1.0) & (t < t0)] > 0.1).all()  # driving into it
    assert (v_cmd[(t > t0 + 0.6) & (t < t0 + 2.0)] == 0.0).all()  # stopped in the dark
    assert (v_cmd[t > t0 + 3.0] > 0).any()  # and on again
    assert s["completed"] and s["cross_track_max_m"] <= 0.05
    print(
        json.dumps(
            {k: s[k] for k in ("converged_s", "cross_track_rms_m", "cross_track_max_m", "blackout")}
        )
    )


def test_bad_options_are_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for bad in (["--speed", "1.5"], ["--blackout", "-1"]):
        assert main(["simulate", "follow", "--out", str(tmp_path / "x"), *bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: follow: --speed")
    (tmp_path / "y").mkdir()
    (tmp_path / "y" / "follow_summary.json").write_text("{}")
    assert main(["simulate", "follow", "--out", str(tmp_path / "y")]) == 2
    assert "--force" in capsys.readouterr().err

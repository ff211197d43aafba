"""``stream follow``: the law within the robot's limits (seeded random property test), stops on
stale/lost/garbage/end, the node over zenoh: zero Twist within 0.5 s, drops counted, SIGINT."""

from __future__ import annotations

import json
import math
import random
import signal
import time

import zenoh

from tagtrail.stream import codec
from tagtrail.stream.follow import (
    PROFILES,
    TWIST,
    Follower,
    Gains,
    Limits,
    decode_twist,
    encode_twist,
)
from tagtrail.stream.session import make_config
from tagtrail.stream.stats import DropError
from tests.stream.helpers import Collector, free_port, loopback, running


def state(
    e: float = 0.0,
    phi: float = 0.0,
    kappa: float = 0.0,
    s: float = 1.0,
    lost: bool = False,
    stamp_ns: int | None = None,
) -> bytes:
    sec, nsec = divmod(time.time_ns() if stamp_ns is None else stamp_ns, 1_000_000_000)
    return json.dumps(
        {
            "stamp_sec": sec,
            "stamp_nanosec": nsec,
            "distance_m": abs(e),
            "heading_error_deg": math.degrees(phi),
            "heading_error_rad": phi,
            "cross_track_m": e,
            "progress_m": s,
            "curvature_1pm": kappa,
            "lookahead_u": 0.0,
            "lookahead_v": 0.0,
            "lost": lost,
        }
    ).encode()


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def wall_ns(self) -> int:
        return int(self.t * 1e9)


def test_twist_is_the_ros_message() -> None:
    t = codec.types()
    V = t["geometry_msgs/msg/Vector3"]
    msg = t[TWIST](linear=V(0.25, 0.0, 0.0), angular=V(0.0, 0.0, -0.5))
    assert codec.serialize(msg, TWIST) == encode_twist(0.25, -0.5)
    assert decode_twist(encode_twist(0.25, -0.5)) == (0.25, -0.5)


def test_never_beyond_the_profiles_limits() -> None:
    """Thousands of random states (errors, headings, curvatures, gaps, lost, end, garbage):
    every command within speed, turning radius and accelerations; stops are zero."""
    rnd = random.Random(28)
    for limits, gains in (PROFILES["limo"][:2], (Limits(), Gains(law="pure_pursuit"))):
        clock = Clock()
        fol = Follower(
            limits,
            gains,
            speed_mps=rnd.uniform(0.1, 2.0),
            path_length_m=20.0,
            max_jump_m=0.0,
            clock=clock,
            wall_ns=clock.wall_ns,
        )
        prev, t_prev, n_drive = (0.0, 0.0), clock.t, 0
        for _ in range(5000):
            clock.t += rnd.choice([0.001, 0.01, 0.033, 0.05, 0.2, rnd.uniform(0, 0.3)])
            kind = rnd.random()
            if kind < 0.05:
                data = rnd.choice(
                    [
                        b"",
                        b"{",
                        b"[1]",
                        b'{"cross_track_m": "x"}',
                        bytes(40),
                        state(e=math.nan),
                        state(kappa=math.inf),
                    ]
                )
            else:
                data = state(
                    rnd.gauss(0, 0.5),
                    rnd.uniform(-math.pi, math.pi),
                    rnd.choice([0.0, rnd.gauss(0, 2.0), rnd.uniform(-50, 50)]),
                    rnd.uniform(0, 21),
                    lost=rnd.random() < 0.05,
                    stamp_ns=clock.wall_ns(),
                )
            try:
                c = fol.on_state(data)
            except DropError:
                continue
            fol.finished = False  # keep driving: the end is tested on its own
            if c.stop:
                assert (c.v, c.omega) == (0.0, 0.0)
            else:
                n_drive += 1
                dt = clock.t - t_prev
                assert 0.0 <= c.v <= limits.max_speed_mps + 1e-12
                assert abs(c.omega) <= limits.yaw_rate_bound(c.v) + 1e-12
                assert abs(c.v - prev[0]) <= limits.max_accel_mps2 * dt + 1e-12
                assert abs(c.omega - prev[1]) <= limits.max_ang_accel_rps2 * dt + 1e-9
            prev, t_prev = (c.v, c.omega), clock.t
        assert n_drive > 2000


def test_stops_lost_end_stale_garbage() -> None:
    clock = Clock()
    limits, gains, _ = PROFILES["limo"]
    fol = Follower(limits, gains, 0.3, path_length_m=5.0, clock=clock, wall_ns=clock.wall_ns)
    for _ in range(20):
        clock.t += 0.033
        c = fol.on_state(state(0.1, 0.0, 0.0, 1.0, stamp_ns=clock.wall_ns()))
    assert not c.stop and c.v > 0.2
    assert fol.on_state(state(lost=True, stamp_ns=clock.wall_ns())).reason == "lost"
    old = clock.wall_ns() - 600_000_000
    for bad, reason in (
        (b"nope", "garbage"),
        (state(e=math.nan), "non_finite"),
        (state(stamp_ns=old), "stale"),
    ):
        try:
            fol.on_state(bad)
            raise AssertionError(f"{bad!r} accepted")
        except DropError as err:
            assert err.reason == reason
    assert fol.watchdog() is None
    clock.t += 0.45
    assert fol.watchdog() is not None  # 0.45 s after the last good pose: stop
    clock.t += 0.1  # the last good state is older than the timeout: any progress goes
    c = fol.on_state(state(s=4.96, stamp_ns=clock.wall_ns()))
    assert (c.v, c.omega, c.reason) == (0.0, 0.0, "end")
    clock.t += 0.033
    assert fol.on_state(state(s=4.9, stamp_ns=clock.wall_ns())).reason == "end"  # stays done


def test_a_jumping_cross_track_is_dropped_until_the_timeout() -> None:
    clock = Clock()
    limits, gains, _ = PROFILES["limo"]
    fol = Follower(limits, gains, 0.3, clock=clock, wall_ns=clock.wall_ns)
    fol.on_state(state(0.02, stamp_ns=clock.wall_ns()))
    clock.t += 0.033
    try:
        fol.on_state(state(2.5, stamp_ns=clock.wall_ns()))  # a bad pose
        raise AssertionError("accepted")
    except DropError as err:
        assert err.reason == "jump"
    clock.t += 0.033
    assert not fol.on_state(state(0.03, stamp_ns=clock.wall_ns())).stop
    dropped = 0
    for _ in range(20):  # a real jump (re-acquired elsewhere): dropped for 0.5 s, then taken
        clock.t += 0.033
        try:
            fol.on_state(state(0.6, stamp_ns=clock.wall_ns()))
        except DropError:
            dropped += 1
    # the documented gate: |Δe| > 0.1 m + v_max·dt while dt ≤ 0.5 s
    rule = sum(
        k * 0.033 <= 0.5 and 0.57 > 0.1 + limits.max_speed_mps * k * 0.033 for k in range(1, 21)
    )
    assert dropped == rule >= 10 and fol.last_e == 0.6


def test_steers_back_towards_the_path() -> None:
    """Left of the path about n = down is the robot's right: it turns left (omega > 0)."""
    clock = Clock()
    limits, gains, _ = PROFILES["limo"]
    for normal_down, sign in ((True, 1.0), (False, -1.0)):
        fol = Follower(
            limits, gains, 0.3, clock=clock, wall_ns=clock.wall_ns, normal_down=normal_down
        )
        for _ in range(30):
            clock.t += 0.033
            c = fol.on_state(state(e=0.2, stamp_ns=clock.wall_ns()))
        assert sign * c.omega > 0.1


def test_node_stops_counts_drops_and_exits_on_sigint() -> None:
    port = free_port()
    args = ["follow", "--profile", "limo", "--listen", loopback(port), "--stats-period", "0"]
    with running(args) as (node,):
        node.wait_for("follow: ready")
        sub = Collector(port, ["cmd_vel"])
        s = zenoh.open(make_config("peer", connect=[loopback(port)]))
        pub = s.declare_publisher("relocalization/state")
        try:
            sub.wait("cmd_vel", 1)  # the first word is a zero Twist
            time.sleep(0.3)
            bad = [b"garbage", state(e=math.nan), b'{"lost": 1}', state(stamp_ns=1)]
            for b in bad:
                pub.put(b)
            for _ in range(30):
                pub.put(state(0.05, 0.0, 0.0, 1.0))
                time.sleep(1 / 30)
            t_last = time.monotonic()
            moving = sub.wait_until("cmd_vel", lambda g: decode_twist(g[-1])[0] > 0, 5)
            n0 = len(moving)
            got = sub.wait_until(
                "cmd_vel",
                lambda g: len(g) > n0 and any(decode_twist(x) == (0.0, 0.0) for x in g[n0:]),
                2,
            )
            t_zero = time.monotonic()
            assert t_zero - t_last <= 0.5, t_zero - t_last
            assert all(decode_twist(x)[0] <= 1.0 for x in got)
        finally:
            pub.undeclare()
            s.close()
        n_before = len(sub.samples["cmd_vel"])
        assert node.stop(sig=signal.SIGINT) == 0, node.output
        time.sleep(0.3)
        last = sub.samples["cmd_vel"][-1]
        sub.close()
        assert len(sub.samples["cmd_vel"]) >= n_before and decode_twist(last) == (0.0, 0.0)
        st = node.stats()
        assert st["dropped"] == {"garbage": 2, "non_finite": 1, "stale": 1}, st
        assert st["shutdown_clean"] and st["shutdown_s"] < 1.0


def test_node_on_the_rmw_zenoh_wire() -> None:
    """``--wire rmw_zenoh``: the Twist on rmw_zenoh's key of ``cmd_vel`` with its attachment,
    the state JSON on its bare key (as relocalize publishes it on that wire)."""
    from tagtrail.stream import wire as W

    port = free_port()
    args = [
        "follow",
        "--profile",
        "limo",
        "--wire",
        "rmw_zenoh",
        "--ros-distro",
        "jazzy",
        "--listen",
        loopback(port),
        "--stats-period",
        "0",
    ]
    with running(args) as (node,):
        node.wait_for("follow: ready")
        s = zenoh.open(make_config("peer", connect=[loopback(port)]))
        key = W.make_wire("rmw_zenoh", s, "jazzy", 0).key("cmd_vel", TWIST)
        assert key.startswith("0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_")
        got: list[tuple[bytes, bytes | None]] = []

        def on(sample: zenoh.Sample) -> None:
            att = sample.attachment
            got.append((sample.payload.to_bytes(), None if att is None else att.to_bytes()))

        sub = s.declare_subscriber(key, on)
        pub = s.declare_publisher("relocalization/state")
        try:
            deadline = time.monotonic() + 10
            while not any(decode_twist(p)[0] > 0 for p, _ in got):
                assert time.monotonic() < deadline, got[-3:]
                pub.put(state(0.02, 0.0, 0.0, 1.0))
                time.sleep(1 / 30)
        finally:
            pub.undeclare()
            sub.undeclare()
            s.close()
        assert all(a is not None and len(a) == 33 for _, a in got)
        assert node.stop(sig=signal.SIGINT) == 0, node.output


def test_one_bad_pose_at_the_paths_end_does_not_end_the_run() -> None:
    """Defect b: a bad pose re-acquired onto the path's end (a figure eight's end is 0.4 m from
    its start) with a plausible cross-track used to latch ``end``: the robot stopped for good
    mid-path. A progress jump is dropped as one; on a loop progress may wrap end → start."""
    clock = Clock()
    limits, gains, _ = PROFILES["limo"]

    def step(fol: Follower, s: float) -> str:
        clock.t += 0.033
        return fol.on_state(state(0.01, s=s, stamp_ns=clock.wall_ns())).reason

    fol = Follower(limits, gains, 0.3, path_length_m=9.0, clock=clock, wall_ns=clock.wall_ns)
    assert [step(fol, s) for s in (0.30, 0.31, 0.32)] == ["drive"] * 3
    try:
        step(fol, 8.99)
        raise AssertionError("accepted")
    except DropError as err:
        assert err.reason == "jump" and "progress" in str(err)
    assert step(fol, 0.33) == "drive" and not fol.finished
    loop = Follower(
        limits, gains, 0.3, path_length_m=9.0, clock=clock, wall_ns=clock.wall_ns, closed=True
    )
    assert [step(loop, s) for s in (8.88, 8.91, 8.94, 0.0, 0.03)] == ["drive"] * 5

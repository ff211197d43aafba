"""``tagtrail stream follow``: a reference path follower — the example a student replaces.

Input: the ``…/state`` JSON of ``tagtrail stream relocalize`` (signed ``cross_track_m`` e,
``heading_error_rad`` phi, ``curvature_1pm`` kappa, ``progress_m`` s, ``lost``). Output:
``geometry_msgs/msg/Twist`` on ``cmd_vel`` (``linear.x`` v, ``angular.z`` omega).

Every quantity of the state is measured counter-clockwise about the plane normal n = e1 × e2
(SPEC Conventions): e > 0 left of the path, phi > 0 turned left of it. tagtrail's ``xz`` and
``auto`` planes have n pointing *down* (the camera's y), so "left about n" is the robot's right;
``--plane-normal down`` (the default) turns omega about n into the robot's yaw rate (REP 103,
z up) by a sign flip, ``up`` keeps it (an ``xy`` plane with world z up).

The control law (:func:`control`, pure: numbers in, numbers out):

- **Stanley** (default; Hoffmann et al. 2007, with curvature feed-forward), steering angle of a
  bicycle of wheelbase L, then the yaw rate it gives::

      delta = atan(L·kappa) − phi − atan2(k·e, k_soft + v)      omega = v·tan(delta) / L

- **pure pursuit** on the lookahead point at distance Ld ahead (``--lookahead``, the relocalize
  node's ``lookahead_m``), placed in the path's frame at the match (exact on a straight stretch,
  the path's curvature fed forward)::

      alpha = atan2(−e, sqrt(Ld² − e²)) − phi     omega = v·(2·sin(alpha)/Ld + kappa)

phi is the camera's heading against the tangent of the reference's (camera) path: a camera d
ahead of the turning centre (the rear axle; ``--camera-forward``) on a curve is headed
atan(d·kappa) outward of its path's tangent, so both laws steer on phi + atan(d·kappa) (0 on
the path).

Speed: v = min(--speed, sqrt(a_lat_max/|kappa|), sqrt(2·a_max·(length − s))) — slower in curves
and ramping down to the path's end. Limits (:class:`Limits`, ``--profile limo`` or flags):
|omega| ≤ v / R_min (the turning radius), |Δv| ≤ a_max·dt, |Δomega| ≤ alpha_max·dt, 0 ≤ v ≤
v_max. A zero Twist (stop, not rate-limited) when the last good state is older than
``--timeout`` (0.5 s; by arrival, and by its stamp unless ``--no-stamp-check``), ``lost``, or
at the path's end (s ≥ length − ``--end-tolerance``). NaN/garbage states are counted (stats
``dropped``) and dropped, and so is a cross-track or a progress that jumps more than
``--max-jump`` (0.1 m, plus v_max·dt) from the last good one within ``--timeout`` (a bad pose: a
robot cannot jump; ``jump``; a closed path's progress may wrap from its end to its start). The
progress gate keeps one bad pose re-acquired onto the path's end (a figure eight's end lies
0.4 m from its start) from stopping the robot for good mid-path. On SIGINT/SIGTERM: a zero
Twist, then the node closes.
"""

from __future__ import annotations

import json
import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any

from tagtrail.stream.node import Node
from tagtrail.stream.stats import DropError

log = logging.getLogger("tagtrail.stream")

TWIST = "geometry_msgs/msg/Twist"
LAWS = ("stanley", "pure_pursuit")
WATCHDOG_S = 0.05  # the stale-pose check's period (the Node's main loop wakes every 50 ms)


@dataclass(frozen=True)
class Limits:
    """The robot's limits: speed (m/s), turning radius (m; 0: turns in place), linear and
    angular acceleration (m/s², rad/s²), lateral acceleration in curves (m/s²)."""

    max_speed_mps: float = 0.5
    min_turn_radius_m: float = 0.0
    max_accel_mps2: float = 1.0
    max_ang_accel_rps2: float = 4.0
    max_lat_accel_mps2: float = 0.5
    max_yaw_rate_rps: float = 2.0

    def yaw_rate_bound(self, v: float) -> float:
        """Largest |omega| allowed at speed v."""
        if self.min_turn_radius_m > 0:
            return min(self.max_yaw_rate_rps, abs(v) / self.min_turn_radius_m)
        return self.max_yaw_rate_rps


@dataclass(frozen=True)
class Gains:
    """The law and its parameters (see the module docstring)."""

    law: str = "stanley"
    k: float = 2.0  # Stanley's cross-track gain (1/s)
    k_soft: float = 0.1  # m/s: keeps the cross-track term finite at low speed
    wheelbase_m: float = 0.2
    lookahead_m: float = 0.3  # pure pursuit's Ld
    camera_forward_m: float = 0.0  # d: the pose (camera) ahead of the turning centre


# The LIMO (NOTES "The LIMO"): 1 m/s, Ackermann R_min 0.4 m, wheelbase 0.2 m; key cmd_vel.
PROFILES: dict[str, tuple[Limits, Gains, str]] = {
    "limo": (
        Limits(
            max_speed_mps=1.0,
            min_turn_radius_m=0.4,
            max_accel_mps2=1.0,
            max_ang_accel_rps2=4.0,
            max_lat_accel_mps2=0.5,
            max_yaw_rate_rps=2.5,
        ),
        Gains(wheelbase_m=0.2, camera_forward_m=0.084),
        "cmd_vel",
    ),
}


def control(e: float, phi: float, kappa: float, v: float, g: Gains) -> float:
    """Yaw rate (rad/s, counter-clockwise about n) of the law at speed ``v`` ≥ 0."""
    phi = phi + math.atan(g.camera_forward_m * kappa)  # phi on the curve when on the path
    if g.law == "pure_pursuit":
        ld = g.lookahead_m
        alpha = math.atan2(-e, math.sqrt(max(ld * ld - e * e, 1e-6))) - phi
        return v * (2.0 * math.sin(alpha) / ld + kappa)
    delta = math.atan(g.wheelbase_m * kappa) - phi - math.atan2(g.k * e, g.k_soft + v)
    delta = max(-1.4, min(1.4, delta))  # tan stays finite; the radius limit applies after
    return v * math.tan(delta) / g.wheelbase_m


@dataclass
class Command:
    v: float = 0.0
    omega: float = 0.0
    stop: bool = True  # a zero Twist for a reason (not rate-limited)
    reason: str = "start"


class Follower:
    """The node's state: last command, limits, and the per-state step (bytes in → Twist out)."""

    def __init__(
        self,
        limits: Limits,
        gains: Gains,
        speed_mps: float,
        path_length_m: float | None = None,
        end_tolerance_m: float = 0.05,
        timeout_s: float = 0.5,
        stamp_check: bool = True,
        normal_down: bool = True,
        max_jump_m: float = 0.1,
        clock: Callable[[], float] = time.monotonic,
        closed: bool = False,
        wall_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.limits, self.gains = limits, gains
        self.speed = min(speed_mps, limits.max_speed_mps)
        self.length = path_length_m
        self.end_tol = end_tolerance_m
        self.timeout_s = timeout_s
        self.stamp_check = stamp_check
        self.sign = -1.0 if normal_down else 1.0
        self.last = Command()
        self.t_last_cmd: float | None = None
        self.t_last_good: float | None = None
        self.finished = False
        self.lock = threading.Lock()
        self.clock, self.wall_ns = clock, wall_ns
        self.max_jump = max_jump_m
        self.closed = closed  # a loop: progress wraps from length to 0
        self.last_e = math.nan
        self.last_s = math.nan

    def parse(self, data: bytes, now_wall_ns: int) -> dict[str, Any]:
        """The state document, checked; :class:`DropError` (counted) for anything else."""
        try:
            doc = json.loads(data)
        except (ValueError, UnicodeDecodeError) as err:
            raise DropError("garbage", f"not JSON: {err}") from None
        if not isinstance(doc, dict):
            raise DropError("garbage", "not a JSON object")
        out: dict[str, Any] = {}
        for k in ("cross_track_m", "heading_error_rad", "curvature_1pm", "progress_m"):
            x = doc.get(k)
            if isinstance(x, bool) or not isinstance(x, int | float):
                raise DropError("garbage", f"{k} is {x!r}")
            if not math.isfinite(x):
                raise DropError("non_finite", f"{k} is {x!r}")
            out[k] = float(x)
        out["lost"] = doc.get("lost") is True
        sec, nsec = doc.get("stamp_sec"), doc.get("stamp_nanosec")
        if not (isinstance(sec, int) and isinstance(nsec, int)):
            raise DropError("garbage", f"stamp {sec!r}.{nsec!r}")
        age = (now_wall_ns - (sec * 1_000_000_000 + nsec)) * 1e-9
        if self.stamp_check and age > self.timeout_s:
            raise DropError("stale", f"pose {age:.3f} s old")
        return out

    def on_state(self, data: bytes) -> Command:
        """One state in → the command to publish (DropError for bad input: nothing sent)."""
        now = self.clock()
        s = self.parse(data, self.wall_ns())
        with self.lock:
            self._gate(now, s["cross_track_m"], s["progress_m"])
            self.t_last_good = now
            if s["lost"]:
                return self._stop(now, "lost")
            if self.length is not None and s["progress_m"] >= self.length - self.end_tol:
                self.finished = True
            if self.finished:
                return self._stop(now, "end")
            return self._drive(now, s)

    def _gate(self, now: float, e: float, s: float) -> None:
        """Drop a cross-track or progress that jumps more than ``max_jump`` (+ what the robot can
        move) from the last good one — a bad pose, not a motion; after ``timeout_s`` anything
        goes."""
        if self.max_jump > 0 and self.t_last_good is not None and math.isfinite(self.last_e):
            dt = now - self.t_last_good
            bound = self.max_jump + self.limits.max_speed_mps * dt
            ds = abs(s - self.last_s)
            if self.closed and self.length is not None:
                ds = min(ds, abs(self.length - ds))  # a loop: its end meets its start
            if dt <= self.timeout_s:
                if abs(e - self.last_e) > bound:
                    raise DropError("jump", f"cross-track {self.last_e:.3f} -> {e:.3f} m")
                if ds > bound:
                    raise DropError("jump", f"progress {self.last_s:.3f} -> {s:.3f} m")
        self.last_e, self.last_s = e, s

    def _drive(self, now: float, s: dict[str, Any]) -> Command:
        lim, kappa = self.limits, s["curvature_1pm"]
        v_ref = self.speed
        if abs(kappa) > 1e-9:
            v_ref = min(v_ref, math.sqrt(lim.max_lat_accel_mps2 / abs(kappa)))
        if self.length is not None:
            v_ref = min(
                v_ref,
                math.sqrt(
                    2 * lim.max_accel_mps2 * max(self.length - self.end_tol - s["progress_m"], 0.0)
                ),
            )
        dt = 0.1 if self.t_last_cmd is None else min(now - self.t_last_cmd, 0.1)
        prev = self.last
        v = max(0.0, min(v_ref, prev.v + lim.max_accel_mps2 * dt, lim.max_speed_mps))
        v = max(v, prev.v - lim.max_accel_mps2 * dt)
        w = self.sign * control(s["cross_track_m"], s["heading_error_rad"], kappa, v, self.gains)
        bound = lim.yaw_rate_bound(v)
        w = max(-bound, min(bound, w))
        w = max(
            prev.omega - lim.max_ang_accel_rps2 * dt,
            min(prev.omega + lim.max_ang_accel_rps2 * dt, w),
        )
        w = max(-bound, min(bound, w))  # the radius wins over the angular acceleration
        return self._set(now, Command(v, w, False, "drive"))

    def _stop(self, now: float, reason: str) -> Command:
        return self._set(now, Command(0.0, 0.0, True, reason))

    def _set(self, now: float, cmd: Command) -> Command:
        self.last, self.t_last_cmd = cmd, now
        return cmd

    def watchdog(self, period_s: float = 0.05) -> Command | None:
        """A stop when the last good state is older than ``timeout_s − 2·period_s``: run every
        ``period_s`` (give or take a loop), the zero Twist is out within ``timeout_s``."""
        now = self.clock()
        with self.lock:
            stale = (
                self.t_last_good is None or now - self.t_last_good > self.timeout_s - 2 * period_s
            )
            if stale:
                return self._stop(now, "timeout")
        return None


def encode_twist(v: float, omega: float) -> bytes:
    """CDR (little endian) of a Twist: linear (v, 0, 0), angular (0, 0, omega)."""
    return struct.pack("<4s6d", b"\x00\x01\x00\x00", v, 0.0, 0.0, 0.0, 0.0, omega)


ZERO = encode_twist(0.0, 0.0)


def decode_twist(data: bytes) -> tuple[float, float]:
    """``(linear.x, angular.z)`` of a CDR Twist."""
    if len(data) < 52:
        raise DropError("truncated", f"Twist of {len(data)} bytes")
    vals = struct.unpack_from("<6d", data, 4)
    return vals[0], vals[5]


def with_profile(
    limits: Limits, gains: Gains, profile: str | None, overrides: dict[str, Any]
) -> tuple[Limits, Gains, str]:
    """Limits, gains and key of ``profile`` (built-in defaults for None) with ``overrides``
    (field name → value, None: not given) applied."""
    key = "cmd_vel"
    if profile in PROFILES:
        limits, gains, key = PROFILES[profile]
    lf = {k: v for k, v in overrides.items() if v is not None and hasattr(limits, k)}
    gf = {k: v for k, v in overrides.items() if v is not None and hasattr(gains, k)}
    return replace(limits, **lf), replace(gains, **gf), overrides.get("cmd_key") or key


class FollowerNode(Node):
    """A :class:`Node` whose last word is a zero Twist on ``cmd_key``."""

    cmd_key = "cmd_vel"

    def close(self, wait_s: float = 0.3) -> bool:
        if not self._closed:
            try:
                self.publish([(self.cmd_key, ZERO)])
            except Exception as err:  # noqa: BLE001 - shutting down anyway
                log.debug("final zero Twist: %s", err)
        return super().close(wait_s)


def serve(
    fol: Follower,
    node: FollowerNode,
    state_key: str,
    cmd_key: str,
    duration_s: float | None,
    stats_period_s: float,
    stop: threading.Event,
) -> dict[str, Any]:
    """Run the follower on ``node`` until stopped: a zero Twist first, one per state, zeros
    every 50 ms while no good state is fresh, a zero Twist last."""
    node.types.update({state_key: "json", cmd_key: TWIST})
    node.cmd_key = cmd_key
    node.publisher(cmd_key)

    def handler(data: bytes) -> Iterable[tuple[str, bytes]]:
        c = fol.on_state(data)
        return [(cmd_key, encode_twist(c.v, c.omega))]

    def tick() -> None:
        if fol.watchdog(WATCHDOG_S) is not None:
            node.publish([(cmd_key, ZERO)])

    node.subscribe(state_key, handler)
    node.every(WATCHDOG_S, tick)
    return node.run(duration_s, stats_period_s, stop)

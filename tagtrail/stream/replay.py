"""``tagtrail stream replay``: publish recorded poses (or bag topics) at the recorded rate.

Sources: a trajectory file or folder in tagtrail's or the original tool's layouts (read with
:func:`tagtrail.io.layouts.read_trajectory`: ``trajectory.csv``, ``trajetoria_camera.csv``, TUM),
or a bag (rosbag2 folder / ``.mcap`` / ``.db3``, ROS 1 ``.bag``) with a pose topic of type
``geometry_msgs/msg/PoseStamped`` (also ``PoseWithCovarianceStamped``, ``nav_msgs/msg/Odometry``:
their pose is sent; without ``--topic`` a bag's wheel odometry is taken only when it is its one
pose topic). Stamps are the recorded ones; the pause between two poses is their stamp
difference divided by ``rate`` (``0``: as fast as possible; a stamp going back: no pause).

Before publishing, replay waits (``--wait``) for a subscriber on every key: zenoh drops samples
nobody subscribes to, silently. A key still without one is an error (exit 2, nothing published)
unless ``--publish-anyway``.

With ``topics``, a bag's messages of those topics are published unchanged instead, each on the
key zenoh-bridge-ros2dds would use (the topic without its leading ``/``), CDR with its
encapsulation header (ROS 1 messages are converted), paced by the bag's log times: e.g. the
``/detections`` + ``/camera_info`` of a recording, to feed ``tagtrail stream localize``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tagtrail.errors import SourceError, TagtrailError
from tagtrail.io import msgs
from tagtrail.io.bags import bag_path, open_bag
from tagtrail.io.layouts import TRAJECTORY_NAMES, read_trajectory
from tagtrail.schemas.artifacts import POSE_COLS
from tagtrail.stream import codec
from tagtrail.stream.stats import lone_outliers, say

log = logging.getLogger("tagtrail.stream")
POSE_MSGTYPES = tuple(codec.POSE_TYPES.values())


@dataclass(frozen=True)
class Poses:
    """Recorded poses: ``t_ns (N,)`` int64, ``values (N, 7)`` (x, y, z, qx, qy, qz, qw),
    ``frames`` one frame id per pose."""

    t_ns: NDArray[np.int64]
    values: NDArray[np.float64]
    frames: list[str]

    def __len__(self) -> int:
        return len(self.t_ns)


def _is_trajectory(path: Path) -> bool:
    if path.is_file():
        return path.suffix in (".csv", ".tum", ".txt")
    return path.is_dir() and any((path / n).is_file() for n in TRAJECTORY_NAMES)


def load_poses(source: Path, topic: str | None = None, frame_id: str | None = None) -> Poses:
    """The poses of a trajectory file/folder or of a bag's pose topic (module docstring).

    ``frame_id`` overrides the frame (trajectory files have none: default ``map``).
    """
    source = Path(source)
    if not source.exists():
        raise SourceError(f"{source}: no such file or folder")
    if _is_trajectory(source):
        traj = read_trajectory(source)
        if len(traj) == 0:
            raise SourceError(f"{source}: no poses to replay (only a header)")
        return Poses(
            traj["t_ns"].to_numpy(np.int64),
            traj[POSE_COLS].to_numpy(np.float64),
            [frame_id or "map"] * len(traj),
        )
    t, vals, frames = _read_bag(source, topic)
    if frame_id is not None:
        frames = [frame_id] * len(frames)
    return Poses(
        np.asarray(t, dtype=np.int64), np.asarray(vals, dtype=np.float64).reshape(-1, 7), frames
    )


def _read_bag(path: Path, topic: str | None) -> tuple[list[int], list[list[float]], list[str]]:
    bag = bag_path(path)
    reader = open_bag(bag)
    try:
        types = {c.topic: c.msgtype for c in reader.connections}
        listing = ", ".join(f"{t} ({m})" for t, m in sorted(types.items())) or "none"
        if topic is None:
            cands = sorted(t for t, m in types.items() if m in POSE_MSGTYPES)
            # a robot's bag also has its wheel odometry (odom frame, not a map pose): a pose
            # topic of another type comes first; odometry is taken only when alone
            posed = [t for t in cands if types[t] != "nav_msgs/msg/Odometry"]
            cands = posed or cands
            if len(cands) != 1:
                raise SourceError(
                    f"{bag}: {'several' if cands else 'no'} pose topics; name one "
                    f"with --topic (topics: {listing})"
                )
            topic = cands[0]
        if types.get(topic) not in POSE_MSGTYPES:
            raise SourceError(f"{bag}: topic {topic} is not a pose topic (topics: {listing})")
        conns = [c for c in reader.connections if c.topic == topic]
        t_ns, vals, frames = [], [], []
        for conn, t_recv, raw in reader.messages(connections=conns):
            msg: Any = reader.deserialize(raw, conn.msgtype)  # one of POSE_MSGTYPES
            p = msg.pose if conn.msgtype == msgs.POSE_STAMPED else msg.pose.pose
            st = msg.header.stamp
            stamp = int(st.sec) * 1_000_000_000 + int(st.nanosec)
            t_ns.append(stamp or int(t_recv))
            vals.append(
                [
                    p.position.x,
                    p.position.y,
                    p.position.z,
                    p.orientation.x,
                    p.orientation.y,
                    p.orientation.z,
                    p.orientation.w,
                ]
            )
            frames.append(str(msg.header.frame_id))
    except SourceError:
        raise
    except Exception as err:
        raise SourceError(f"{bag}: cannot read topic {topic}: {err}") from err
    finally:
        reader.close()
    if not t_ns:
        raise SourceError(f"{bag}: topic {topic} has no messages")
    return t_ns, vals, frames


@dataclass(frozen=True)
class Messages:
    """What to publish, in order: ``t_ns (N,)`` pacing times, ``keys`` and ``payloads``;
    ``types``: each key's ROS message type (the rmw_zenoh wire needs it)."""

    t_ns: NDArray[np.int64]
    keys: list[str]
    payloads: list[bytes]
    types: dict[str, str] = field(default_factory=dict)


def pose_messages(poses: Poses, key: str) -> Messages:
    """CDR ``PoseStamped`` of every pose on ``key`` (encoded before publishing starts)."""
    encoders: dict[str, codec.PoseStampedEncoder] = {}
    sec, nsec = np.divmod(poses.t_ns, 1_000_000_000)
    out = []
    for s, n, v, f in zip(
        sec.tolist(), nsec.tolist(), poses.values.tolist(), poses.frames, strict=True
    ):
        enc = encoders.get(f) or encoders.setdefault(f, codec.PoseStampedEncoder(f))
        out.append(enc(s, n, *v))
    return Messages(poses.t_ns, [key] * len(out), out, {key: msgs.POSE_STAMPED})


def bag_messages(source: Path, topics: list[str], optional: Sequence[str] = ()) -> Messages:
    """The messages of ``topics`` in a bag, unchanged CDR, keyed by topic without ``/``
    (``optional`` ones only when the bag has them)."""
    bag = bag_path(source)
    reader = open_bag(bag)
    try:
        have = {c.topic for c in reader.connections}
        missing = [t for t in topics if t not in have and t not in optional]
        if missing:
            raise SourceError(
                f"{bag}: no topic {', '.join(missing)} (topics: "
                f"{', '.join(sorted(have)) or 'none'})"
            )
        conns = [c for c in reader.connections if c.topic in topics]
        ros1 = bag.suffix == ".bag"
        t_ns, keys, data = [], [], []
        for conn, t, raw in reader.messages(connections=conns):
            t_ns.append(int(t))
            keys.append(conn.topic.lstrip("/"))
            cdr = msgs.typestore().ros1_to_cdr(raw, conn.msgtype) if ros1 else raw
            data.append(bytes(cdr))
    finally:
        reader.close()
    if not data:
        raise SourceError(f"{bag}: topics {', '.join(topics)} have no messages")
    types = {c.topic.lstrip("/"): c.msgtype for c in conns}
    return Messages(np.asarray(t_ns, dtype=np.int64), keys, data, types)


def schedule_s(t_ns: NDArray[np.int64], rate: float) -> NDArray[np.float64]:
    """Send times (s from the first message) at ``rate`` × the recorded speed; all 0 for 0.

    A stamp going back: no pause. A lone outlier stamp (:func:`~tagtrail.stream.stats.
    lone_outliers`: far future, far past, zero) is sent with its predecessor, so it neither
    stalls the replay nor sends the messages after it at once (logged once)."""
    if rate <= 0 or len(t_ns) == 0:
        return np.zeros(len(t_ns))
    t = np.asarray(t_ns, dtype=np.int64)
    lone = lone_outliers(t)
    if lone.any():
        k = np.flatnonzero(lone)
        log.warning(
            "replay: %d lone stamp outlier(s), e.g. message %d at %d.%09d s between "
            "stamps %s s: sent without a pause",
            len(k),
            k[0],
            t[k[0]] // 10**9,
            t[k[0]] % 10**9,
            " and ".join(f"{t[j] / 1e9:.3f}" for j in (k[0] - 1, k[0] + 1) if 0 <= j < len(t)),
        )
        keep = np.where(lone, -1, np.arange(len(t)))
        src = np.maximum.accumulate(keep)  # the last stamp before that is not an outlier
        src[src < 0] = np.flatnonzero(~lone)[0] if (~lone).any() else 0
        t = t[src]
    t = np.maximum.accumulate(t)  # a stamp going back: no pause
    send_s: NDArray[np.float64] = (t - t[0]) * 1e-9 / rate
    return send_s


class NoSubscriber(TagtrailError):
    """Nobody subscribed to a replayed key within ``--wait`` (nothing was published; exit 2)."""


@dataclass(frozen=True)
class Replayed:
    """What :func:`replay` did: messages ``sent``; ``clean`` False if a put was still blocked
    (a congested link) when it stopped."""

    sent: int
    clean: bool = True


def replay(
    session: Any,
    messages: Messages,
    *,
    rate: float = 1.0,
    count: int | None = None,
    wait_s: float = 10.0,
    publish_anyway: bool = False,
    congestion: str = "block",
    express: bool = False,
    stop: threading.Event | None = None,
    wire: Any = None,
    optional: Sequence[str] = (),
) -> Replayed:
    """Publish ``messages`` at ``rate`` (see :func:`schedule_s`).

    First waits up to ``wait_s`` for a subscriber on every key but the ``optional`` ones (a
    profile's wheel odometry, which only some nodes take); raises :class:`NoSubscriber` if a
    key has none then, unless ``publish_anyway`` (a warning, and publishing goes on).
    Puts run on a worker thread, so that ``stop`` (SIGINT/SIGTERM) ends the replay within a
    bounded time even while a put is blocked by a congested subscriber. ``wire``: the
    :class:`~tagtrail.stream.wire.Wire` to publish on (default: the bridge's).
    """
    from tagtrail.stream.node import CONGESTION
    from tagtrail.stream.session import close_all, wait_matching
    from tagtrail.stream.wire import Wire

    stop = stop or threading.Event()
    n = len(messages.payloads) if count is None else min(count, len(messages.payloads))
    when = schedule_s(messages.t_ns[:n], rate).tolist()
    wire = wire if wire is not None else Wire(session)
    pubs = {
        k: wire.declare_publisher(
            k, messages.types.get(k), congestion_control=CONGESTION[congestion], express=express
        )
        for k in dict.fromkeys(messages.keys[:n])
    }
    sent = 0
    failed: list[BaseException] = []
    done = threading.Event()

    def publish() -> None:
        nonlocal sent
        try:
            t0 = time.perf_counter()
            for i in range(n):
                delay = t0 + when[i] - time.perf_counter()
                if stop.is_set() or (delay > 0 and stop.wait(delay)):
                    break
                pubs[messages.keys[i]].put(messages.payloads[i])
                sent += 1
        except BaseException as err:  # noqa: BLE001 - re-raised by the caller's thread
            failed.append(err)
        finally:
            done.set()

    clean = True
    try:
        deadline = time.monotonic() + wait_s
        alone = [
            k
            for k, pub in pubs.items()
            if k not in optional
            and not wait_matching(pub, max(deadline - time.monotonic(), 0.0), stop)
        ]
        if stop.is_set():
            return Replayed(0)
        if alone:
            what = f"no subscriber on {', '.join(alone)} after {wait_s:g} s"
            if not publish_anyway:
                raise NoSubscriber(
                    f"replay: {what}; nothing published (--publish-anyway to publish regardless)"
                )
            log.warning("replay: %s; publishing anyway", what)
        t0 = time.perf_counter()
        threading.Thread(target=publish, name="replay", daemon=True).start()
        while not done.wait(0.05):
            if stop.is_set():
                clean = done.wait(0.3)  # a put blocked by a congested link cannot hold us
                break
        if failed:
            raise failed[0]
        dt = time.perf_counter() - t0
        say(
            f"replay: published {sent} messages on {', '.join(pubs)} in {dt:.2f} s "
            f"({sent / max(dt, 1e-9):.0f}/s)"
        )
        if clean:
            time.sleep(0.05)  # let the last samples leave before the session closes
    finally:
        if clean:
            close_all(None, list(pubs.values()))
    return Replayed(sent, clean)

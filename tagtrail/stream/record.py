"""``tagtrail stream record OUT``: a rosbag2 of the topics a robot's zenoh-bridge-ros2dds forwards.

The bridge publishes each ROS topic on the key = topic without its leading ``/``, the payload
being the message's CDR with its encapsulation header (SPEC Streaming). The recorder writes
those bytes unchanged, so header stamps are kept as sent; the log time of each message is its
receive time on this machine. The bag (MCAP or sqlite3, via rosbags'
:class:`~rosbags.rosbag2.Writer`: every topic with its full message definition) is kept readable
by :class:`~tagtrail.stream.bagwriter.CrashSafeWriter` while it grows.

Topics: ``--topic NAME[:TYPE]`` (repeatable), a profile's (:mod:`tagtrail.schemas.profiles`),
or, with neither, every topic the bridge announces on its admin space (zenoh liveliness tokens
``@/<zid>/@ros2_lv/MP/<key>/<type>/<qos>``, ``/`` written ``§``), which also gives the types of
``--topic`` names without one.

Zenoh callbacks only copy the payload into a queue; one writer thread writes, so a slow disk
never stalls the session (past ``max_queue_mb`` queued, samples are dropped and counted). The
first message of each topic is decoded as its declared type: a key carrying another type stops
the recording with one line. So do a key with no message after ``wait_s`` and a full disk;
every message recorded until then is kept in a readable bag.
"""

from __future__ import annotations

import difflib
import logging
import re
import struct
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import zenoh

from tagtrail.errors import SourceError, SpecError, StorageError, TagtrailError
from tagtrail.io import msgs
from tagtrail.schemas.profiles import Profile
from tagtrail.stream.bagwriter import CrashSafeWriter, is_full_disk
from tagtrail.stream.stats import StampOrder, say

log = logging.getLogger("tagtrail.stream")
ADMIN_KEYS = ("@/*/@ros2_lv/MP/**", "@ros2_lv/*/MP/**")  # zenoh 1.x bridges, then 0.x ones
SKIP_TOPICS = {"/rosout", "/parameter_events"}


@dataclass(frozen=True)
class TopicSpec:
    """A topic to record: ROS ``topic`` (``/…``), its ROS 2 ``msgtype``, zenoh ``key``;
    ``optional``: recorded when it comes, never waited for (a profile's wheel odometry)."""

    topic: str
    msgtype: str
    optional: bool = False

    @property
    def key(self) -> str:
        return self.topic.lstrip("/")


def normalize_type(name: str) -> str:
    """``sensor_msgs/Image``, ``sensor_msgs::msg::dds_::Image_`` → ``sensor_msgs/msg/Image``;
    a type the typestore does not know is a :class:`SpecError` with a did-you-mean."""
    text = name.strip().replace("::dds_::", "::").replace("::", "/")
    parts = [p for p in text.split("/") if p]
    if len(parts) == 2:
        parts.insert(1, "msg")
    if parts and parts[-1].endswith("_"):
        parts[-1] = parts[-1][:-1]
    full = "/".join(parts)
    known = msgs.typestore().types
    if full not in known:
        hint = difflib.get_close_matches(full, list(known), n=1)
        extra = f" (did you mean {hint[0]}?)" if hint else ""
        raise SpecError(f"unknown message type {name!r}{extra}")
    return full


def parse_topic(text: str) -> tuple[str, str | None]:
    """``/camera/image:sensor_msgs/msg/Image`` → (``/camera/image``, type or None)."""
    name, _, typ = text.partition(":")
    name = "/" + name.strip().strip("/")
    if name == "/" or not re.fullmatch(r"/[A-Za-z0-9_/~{}]+", name):
        raise SpecError(
            f"--topic {text!r}: not a ROS topic name (write NAME[:TYPE], e.g. "
            "/camera_info:sensor_msgs/msg/CameraInfo)"
        )
    return name, normalize_type(typ) if typ.strip() else None


def discover(session: Any, timeout_s: float = 2.0) -> dict[str, str]:
    """``{topic: type}`` of the publishers a zenoh-bridge-ros2dds announces (module docstring);
    empty when no bridge answers. Topics of types the typestore lacks are left out (logged)."""
    found: dict[str, str] = {}
    for pattern in ADMIN_KEYS:
        try:
            replies = session.liveliness().get(pattern, timeout=timeout_s)
        except Exception as err:  # noqa: BLE001 - no admin space: nothing discovered
            log.debug("liveliness get %s: %s", pattern, err)
            continue
        for reply in replies:
            ok = getattr(reply, "ok", None)
            if ok is None:
                continue
            parts = str(ok.key_expr).split("/")
            i = parts.index("MP") if "MP" in parts else -1
            if i < 0 or len(parts) < i + 3:
                continue
            topic = "/" + parts[i + 1].replace("§", "/").strip("/")
            try:
                found[topic] = normalize_type(parts[i + 2].replace("§", "/"))
            except SpecError:
                log.warning(
                    "record: %s has type %s, unknown here; not recorded",
                    topic,
                    parts[i + 2].replace("§", "/"),
                )
        if found:
            break
    return {t: m for t, m in sorted(found.items()) if t not in SKIP_TOPICS}


def resolve_topics(
    given: list[str], profile: Profile | None, discovered: dict[str, str] | None
) -> list[TopicSpec]:
    """The topics to record: ``--topic`` names (a missing type from the profile or the bridge),
    else the profile's, else every discovered one. A type given that differs from the one the
    bridge announces is an error (the payloads would not decode)."""
    known = dict(profile.record) if profile else {}
    bridge = discovered or {}
    specs: dict[str, str] = {}
    for text in given:
        name, typ = parse_topic(text)
        typ = typ or known.get(name) or bridge.get(name)
        if typ is None:
            raise SpecError(
                f"--topic {name}: give its type (NAME:TYPE, e.g. "
                f"{name}:sensor_msgs/msg/Image); no profile or bridge names it"
            )
        specs[name] = typ
    if not given:
        specs = dict(profile.record) if profile else dict(bridge)
    if not specs:
        raise SpecError(
            "nothing to record: give --topic NAME:TYPE (repeatable) or --profile "
            "NAME; no zenoh-bridge-ros2dds announced topics on the admin space"
        )
    for name, typ in specs.items():
        if name in bridge and bridge[name] != typ:
            raise SpecError(f"{name}: the bridge publishes it as {bridge[name]}, not {typ}")
    optional = set(profile.optional) if profile and not given else set()
    return [TopicSpec(n, t, n in optional) for n, t in specs.items()]


def parse_size(text: str) -> int:
    """``500M``, ``2G``, ``1.5GB``, ``100000`` → bytes (K, M, G, T = powers of 1000)."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([kKmMgGtT]?)[bB]?\s*", text)
    if not m or float(m.group(1)) <= 0:
        raise SpecError(f"--max-size {text!r}: write a size such as 500M or 2G")
    scale = {"": 1, "k": 10**3, "m": 10**6, "g": 10**9, "t": 10**12}[m.group(2).lower()]
    return int(float(m.group(1)) * scale)


@dataclass
class _Topic:
    spec: TopicSpec
    count: int = 0
    last_count: int = 0
    checked: bool = False
    stamp_at: int | None = None  # byte offset of header.stamp in the CDR payload, if any
    order: StampOrder = field(default_factory=StampOrder)


@dataclass
class Recorded:
    """What a recording did: per-topic counts, drops by reason, why it stopped."""

    counts: dict[str, int]
    dropped: dict[str, int]
    reason: str
    seconds: float
    size_bytes: int
    out_of_order: dict[str, int] = field(default_factory=dict)
    stamp_outliers: dict[str, int] = field(default_factory=dict)


class Recorder:
    """Subscribe to ``topics`` on ``session`` and write them into ``writer`` (module docstring)."""

    def __init__(
        self,
        session: Any,
        topics: list[TopicSpec],
        writer: CrashSafeWriter,
        *,
        wait_s: float = 10.0,
        max_size: int | None = None,
        max_queue_mb: float = 1024.0,
        wire: Any = None,
    ) -> None:
        from tagtrail.stream.wire import Wire

        self.session = session
        self.wire = wire if wire is not None else Wire(session)  # the keys to subscribe
        self.writer = writer
        self.topics = {t.key: _Topic(t) for t in topics}
        self.wait_s = wait_s
        self.max_size = max_size
        self.max_queue = int(max_queue_mb * 1e6)
        self.dropped: Counter[str] = Counter()
        self._queue: deque[tuple[_Topic, int, bytes]] = deque()
        self._queued = 0
        self._cond = threading.Condition()
        self._closing = False
        self._subs: list[Any] = []
        self.failure: BaseException | None = None
        self.stopped = threading.Event()  # set by the writer thread on failure / max size
        self.reason = ""

    def _callback(self, topic: _Topic) -> Any:
        def on_sample(sample: Any) -> None:
            t_ns = time.time_ns()  # receive time = the log time
            if self._closing:
                return
            if sample.kind != zenoh.SampleKind.PUT:
                self.dropped["delete"] += 1
                return
            data = sample.payload.to_bytes()
            with self._cond:
                if self._queued + len(data) > self.max_queue:
                    self.dropped["queue_full"] += 1
                    return
                self._queue.append((topic, t_ns, data))
                self._queued += len(data)
                self._cond.notify()

        return on_sample

    def _check(self, topic: _Topic, data: bytes) -> None:
        """The first message of a topic must decode as its type (else: stop, one line)."""
        from tagtrail.stream.codec import CodecError, deserialize, serialize

        mt = topic.spec.msgtype
        try:
            msg = deserialize(data, mt)
            size = len(serialize(msg, mt))
        except CodecError as err:
            raise SourceError(
                f"key {topic.spec.key}: the messages are not {mt} ({err}); give "
                f"its type with --topic {topic.spec.topic}:TYPE"
            ) from err
        if abs(size - len(data)) > 3:  # decoded, but not the whole payload: another type
            raise SourceError(
                f"key {topic.spec.key}: the messages are not {mt} ({len(data)} "
                f"bytes, a {mt} of those fields is {size}); give its type with "
                f"--topic {topic.spec.topic}:TYPE"
            )
        fields = msgs.typestore().fielddefs[mt][1]
        if fields and fields[0][0] == "header":
            topic.stamp_at = 4
        topic.checked = True

    def _note_stamp(self, topic: _Topic, data: bytes) -> None:
        if topic.stamp_at is None or len(data) < 12:
            return
        fmt = "<iI" if data[1] == 1 else ">iI"
        sec, nanosec = struct.unpack_from(fmt, data, 4)
        topic.order.note(sec * 1_000_000_000 + nanosec)

    def _write_loop(self) -> None:
        try:
            self.writer.open()
            while True:
                with self._cond:
                    while not self._queue and not self._closing:
                        self._cond.wait(0.2)
                        if not self._queue:
                            break
                    if not self._queue:
                        if self._closing:
                            break
                        self.writer.maybe_flush()
                        continue
                    topic, t_ns, data = self._queue.popleft()
                    self._queued -= len(data)
                if not topic.checked:
                    self._check(topic, data)
                self._note_stamp(topic, data)
                self.writer.write(topic.spec.topic, topic.spec.msgtype, t_ns, data)
                topic.count += 1
                if self.max_size is not None and self.writer.size >= self.max_size:
                    self.reason = f"--max-size reached ({self.writer.size / 1e6:.1f} MB)"
                    self.stopped.set()
                    break
        except BaseException as err:  # noqa: BLE001 - re-raised by run() after the bag is closed
            self.failure = err
            self.stopped.set()
        finally:
            with self._cond:  # once stopped, nothing more is queued
                self._closing = True
        self._close_bag()

    def _close_bag(self) -> None:
        """Close the bag (or, the disk full, keep it as of its last flush)."""
        try:
            if self.failure is not None and is_full_disk(self.failure):
                self.writer.abort()
            else:
                self.writer.close()
        except Exception as err:  # noqa: BLE001 - a full disk at close: keep the last flush
            try:
                self.writer.abort()
            except Exception as again:  # noqa: BLE001
                log.debug("abort: %s", again)
            if self.failure is None:
                self.failure = err

    def line(self, elapsed_s: float, dt_s: float) -> str:
        """``record: 12.0 s, 276.4 MB | /camera 30.0 Hz 360 | … | dropped 0``."""
        parts = [f"record: {elapsed_s:.1f} s, {self.writer.size / 1e6:.1f} MB"]
        for t in self.topics.values():
            rate = (t.count - t.last_count) / max(dt_s, 1e-9)
            t.last_count = t.count
            parts.append(f"{t.spec.topic} {rate:.1f} Hz {t.count}")
        drops = sum(self.dropped.values())
        why = ", ".join(f"{k} {v}" for k, v in sorted(self.dropped.items()))
        return " | ".join(parts) + f" | dropped {drops}" + (f" ({why})" if why else "")

    def run(
        self,
        duration_s: float | None = None,
        stats_period_s: float = 2.0,
        stop: threading.Event | None = None,
    ) -> Recorded:
        """Record until ``stop`` (SIGINT/SIGTERM), ``duration_s``, ``--max-size`` or a failure;
        then close the bag. A failure is raised (one line) after the bag is closed."""
        stop = stop or threading.Event()
        writer = threading.Thread(target=self._write_loop, name="record writer", daemon=True)
        writer.start()
        t0 = time.monotonic()
        try:
            for t in self.topics.values():
                self._subs.append(
                    self.wire.declare_subscriber(t.spec.topic, t.spec.msgtype, self._callback(t))
                )
            names = ", ".join(f"{t.spec.topic} ({t.spec.msgtype})" for t in self.topics.values())
            say(f"record: recording {names} into {self.writer.out} ({self.writer.kind})")
            t_line = t_last = time.monotonic()
            while not stop.is_set() and not self.stopped.is_set():
                now = time.monotonic()
                if duration_s is not None and now - t0 >= duration_s:
                    self.reason = f"--duration {duration_s:g} s"
                    break
                silent = [t for t in self.topics.values() if t.count == 0 and not t.spec.optional]
                if self.wait_s > 0 and now - t0 >= self.wait_s and silent and not self._queue:
                    self.failure = SourceError(
                        f"no message on {', '.join(t.spec.key for t in silent)} after "
                        f"{self.wait_s:g} s: is it published, and forwarded by the bridge? "
                        "(--wait 0 waits for ever)"
                    )
                    break
                if stats_period_s > 0 and now - t_line >= stats_period_s:
                    say(self.line(now - t0, now - t_last))
                    t_line = t_last = now
                stop.wait(0.05)
            if stop.is_set() and not self.reason:
                self.reason = "interrupted"
        finally:
            self._finish(writer)
        seconds = time.monotonic() - t0
        kept = self.writer.kept  # a full disk: what the bag holds, not what was handed to it
        done = Recorded(
            {
                t.spec.topic: t.count if kept is None else kept.get(t.spec.topic, 0)
                for t in self.topics.values()
            },
            dict(self.dropped),
            self.reason or "failed",
            seconds,
            self.writer.size,
            {t.spec.topic: t.order.out_of_order for t in self.topics.values()},
            {t.spec.topic: t.order.outliers for t in self.topics.values()},
        )
        if self.failure is not None:
            raise self._one_line(self.failure, done) from self.failure
        return done

    def _finish(self, writer: threading.Thread) -> None:
        """Undeclare the subscribers, let the writer thread write what is queued and close the
        bag."""
        for s in self._subs:
            try:
                s.undeclare()
            except Exception as err:  # noqa: BLE001 - shutdown goes on
                log.debug("undeclare: %s", err)
        with self._cond:
            self._closing = True
            self._cond.notify()
        writer.join()

    def _one_line(self, err: BaseException, done: Recorded) -> TagtrailError:
        if not self.writer.opened and isinstance(err, TagtrailError):
            return err  # no bag was made (the folder is not left behind)
        kept = f"recorded until then kept in {self.writer.out} ({_counts(done.counts)})"
        if is_full_disk(err):
            return StorageError(
                f"cannot write {self.writer.file}: No space left on device; "
                f"{kept} (up to its last flush)"
            )
        if isinstance(err, TagtrailError):
            return type(err)(f"{err}; {kept}")
        if isinstance(err, OSError):
            return StorageError(f"cannot write {self.writer.file}: {err.strerror}; {kept}")
        return SourceError(f"recording failed: {type(err).__name__}: {err}; {kept}")


def _counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{t} {n}" for t, n in counts.items()) or "no messages"


def summary_line(done: Recorded, writer: CrashSafeWriter) -> str:
    """The last line; header stamps out of order or lone outliers (kept as sent) are named."""
    stamps = "".join(
        f", {what} {_counts({t: n for t, n in per.items() if n})}"
        for what, per in (
            ("stamps out of order:", done.out_of_order),
            ("stamp outliers:", done.stamp_outliers),
        )
        if any(per.values())
    )
    return (
        f"record: {done.reason}: {sum(done.counts.values())} messages in {done.seconds:.1f} "
        f"s ({_counts(done.counts)}), {done.size_bytes / 1e6:.1f} MB into {writer.out}, "
        f"dropped {sum(done.dropped.values())}{stamps}"
    )

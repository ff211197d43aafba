"""The two wires the live nodes speak: zenoh-bridge-ros2dds's (``bridge``) and rmw_zenoh's.

A node names its inputs and outputs by ROS topic and type; a :class:`Wire` turns them into zenoh
entities, so that nodes never branch on the wire:

- ``bridge`` (the default, SPEC Streaming): key = the topic without its leading ``/``, payload =
  CDR with its 4-byte encapsulation header, no attachment, no tokens (the bridge announces the
  ROS side itself). Publishers are plain ``zenoh.Publisher`` objects: the bytes on the wire are
  those of tagtrail before wires existed.
- ``rmw_zenoh`` (``docs/design.md`` of ros2/rmw_zenoh, checked against its sources, Humble 0.1.2+
  and Jazzy+ releases): data key ``<domain>/<topic without leading />/<DDS type>/<type hash>``
  (``std_msgs::msg::dds_::Float64_``; hash ``TypeHashNotSupported`` on Humble, ``RIHS01_<hex>``
  from rosbags' ``Typestore.hash_rihs01`` on Jazzy and later); the same CDR payload; on every
  put a 33-byte attachment: sequence number (int64 LE, from 1, +1 per publisher), source time
  (int64 LE, ns since the epoch), GID length (one byte, 16), the 16-byte GID; a liveliness token
  for the node and for each publisher/subscriber,
  ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/{NN|MP|MS}/<enclave>/<namespace>/<node>[/<topic>/<type>/
  <hash>/<qos>]``, every ``/`` inside a name written ``%`` (so ``ros2 node list`` /
  ``ros2 topic list`` under rmw_zenoh show tagtrail), the QoS string in rmw_zenoh's
  ``qos_to_keyexpr`` form (fields equal to rmw_zenoh's defaults left empty:
  ``::,10:,:,:,,`` for reliable, volatile, keep-last 10). Subscribers take the type name from
  the key and any type hash; they accept samples with the attachment and without it (counted
  as ``without_attachment``; a malformed one as ``bad_attachment``, a jump in a publisher's
  sequence as ``sequence_gaps``).

The GID: rmw_zenoh hashes the entity's token with XXH3-128; tagtrail takes BLAKE2b-128 of the
same token (xxhash is no dependency). Both are 16 bytes fixed per entity; rmw_zenoh only passes
the attachment's GID on to the application (``message_info.publisher_gid``), never checks it.

Topics typed ``json`` (the ``…/state`` document for non-ROS clients) are no ROS messages: both
wires publish them on the bare key (topic without ``/``), without attachment or token.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import os
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cache
from typing import Any

import zenoh

from tagtrail.errors import SpecError

log = logging.getLogger("tagtrail.stream")
WIRES = ("bridge", "rmw_zenoh")
DISTROS = ("humble", "jazzy", "kilted", "rolling")
RMW_ROUTER = "tcp/localhost:7447"  # rmw_zenohd's endpoint as the nodes of a robot reach it
ADMIN_SPACE = "@ros2_lv"
NO_TYPE_HASH = "TypeHashNotSupported"  # Humble: rosidl has no type hashes
JSON = "json"
GID_SIZE = 16
_ATTACHMENT = struct.Struct(f"<qqB{GID_SIZE}s")  # 33 bytes
Callback = Callable[[zenoh.Sample], None]


def handler(callback: Callback, direct: bool) -> Any:
    """``callback`` as a subscriber's handler. zenoh-python calls a plain callable on a thread
    of its own per subscriber (``indirect``), so samples of two keys lose their arrival order;
    ``direct``: called on zenoh's receiving thread, in arrival order across keys (it must only
    hand the sample on, never block nor call zenoh)."""
    return zenoh.handlers.Callback(callback, indirect=False) if direct else callback


@dataclass(frozen=True)
class QoS:
    """The QoS of an endpoint as the RMW enums give it (``rmw/types.h``): reliability 1 reliable,
    2 best effort; durability 1 transient local, 2 volatile; history 1 keep last, 2 keep all.
    Deadline, lifespan and liveliness lease are always rmw_zenoh's defaults (infinite)."""

    reliability: int = 1
    durability: int = 2
    history: int = 1
    depth: int = 10


RMW_DEFAULT_QOS = QoS(reliability=1, durability=2, history=1, depth=42)  # rmw_zenoh's qos.cpp
DEFAULT_QOS = QoS()  # rclcpp's ``QoS(10)``: reliable, volatile, keep last 10


def qos_string(qos: QoS) -> str:
    """The QoS field of a liveliness token: ``rel:dur:hist,depth:dl_s,dl_ns:ls_s,ls_ns:lv,lv_s,
    lv_ns``, each value written only where it differs from rmw_zenoh's default."""
    d = RMW_DEFAULT_QOS

    def f(value: int, default: int) -> str:
        return "" if value == default else str(value)

    return (
        f"{f(qos.reliability, d.reliability)}:{f(qos.durability, d.durability)}:"
        f"{f(qos.history, d.history)},{f(qos.depth, d.depth)}:,:,:,,"
    )


def dds_type(msgtype: str) -> str:
    """``std_msgs/msg/Float64`` → ``std_msgs::msg::dds_::Float64_`` (the name rmw_zenoh keys)."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str:
    """``std_msgs::msg::dds_::Float64_`` → ``std_msgs/msg/Float64``."""
    parts = [p for p in dds.split("::") if p != "dds_"]
    if len(parts) != 3 or not parts[2].endswith("_"):
        raise ValueError(f"not a DDS type name: {dds!r}")
    return f"{parts[0]}/{parts[1]}/{parts[2][:-1]}"


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` as ``%`` (``/`` alone, the root, is ``%``)."""
    return name.replace("/", "%") or "%"


def demangle(chunk: str) -> str:
    return chunk.replace("%", "/")


@cache
def _typestore(distro: str) -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from tagtrail.io.msgs import APRILTAG_MSGS, ISAAC_MSGS

    store = get_typestore(
        {"jazzy": Stores.ROS2_JAZZY, "kilted": Stores.ROS2_KILTED, "rolling": Stores.LATEST}[distro]
    )
    types: dict[str, Any] = {}
    for name, text in {**APRILTAG_MSGS, **ISAAC_MSGS}.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@cache
def type_hash(msgtype: str, distro: str = "humble") -> str:
    """The type-hash key chunk: ``TypeHashNotSupported`` on Humble, else REP-2016's
    ``RIHS01_<sha256>`` of the distro's definition of ``msgtype``."""
    check_distro(distro)
    if distro == "humble":
        return NO_TYPE_HASH
    try:
        return str(_typestore(distro).hash_rihs01(msgtype))
    except Exception as err:  # rosbags: KeyError / TypesysError for an unknown type
        raise SpecError(f"no {distro} definition of {msgtype}: {err}") from err


def check_distro(distro: str) -> str:
    if distro not in DISTROS:
        raise SpecError(f"--ros-distro {distro!r}: use one of {', '.join(DISTROS)}")
    return distro


def attachment(seq: int, t_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of an rmw_zenoh publication."""
    return _ATTACHMENT.pack(seq, t_ns, GID_SIZE, gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``(sequence number, source time ns, GID)``; ValueError if ``data`` is not 33 bytes with a
    GID length of 16."""
    if len(data) != _ATTACHMENT.size:
        raise ValueError(f"{len(data)} bytes, not {_ATTACHMENT.size}")
    seq, t_ns, n, gid = _ATTACHMENT.unpack(data)
    if n != GID_SIZE:
        raise ValueError(f"GID length {n}, not {GID_SIZE}")
    return seq, t_ns, gid


def gid_of(token: str) -> bytes:
    """The 16-byte GID of an entity: BLAKE2b-128 of its liveliness token (module docstring)."""
    return hashlib.blake2b(token.encode(), digest_size=GID_SIZE).digest()


@dataclass(frozen=True)
class Endpoint:
    """What an rmw_zenoh liveliness token says (:func:`parse_token`)."""

    domain_id: int
    zid: str
    nid: str
    eid: str
    kind: str
    enclave: str
    namespace: str
    node: str
    topic: str | None = None
    dds_type: str | None = None
    type_hash: str | None = None
    qos: str | None = None


def parse_token(key: str) -> Endpoint | None:
    """The entity of a liveliness token (None if ``key`` is not one)."""
    parts = key.split("/")
    if len(parts) not in (9, 13) or parts[0] != ADMIN_SPACE or not parts[1].isdigit():
        return None
    ep = Endpoint(
        domain_id=int(parts[1]),
        zid=parts[2],
        nid=parts[3],
        eid=parts[4],
        kind=parts[5],
        enclave=demangle(parts[6]),
        namespace=demangle(parts[7]),
        node=demangle(parts[8]),
    )
    if len(parts) == 9:
        return ep
    return replace(
        ep, topic=demangle(parts[9]), dds_type=parts[10], type_hash=parts[11], qos=parts[12]
    )


class Wire:
    """The ``bridge`` wire (module docstring); the base of :class:`RmwZenohWire`.

    ``declare_publisher`` returns an object with ``put(payload)``, ``undeclare()`` and
    ``matching_status``; ``declare_subscriber`` calls ``callback(sample)`` for each sample and
    returns an object with ``undeclare()``.
    """

    name = "bridge"

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.counts: Counter[str] = Counter()

    def key(self, topic: str, msgtype: str | None = None) -> str:
        """The zenoh key of ``topic`` carrying ``msgtype``."""
        key = topic.strip("/")
        if not key:
            raise SpecError(f"{topic!r} is no topic name")
        return key

    def declare_node(self, name: str) -> None:
        """Announce this process as a ROS node (the bridge wire has nothing to announce)."""

    def declare_publisher(self, topic: str, msgtype: str | None, **options: Any) -> Any:
        return self.session.declare_publisher(self.key(topic, msgtype), **options)

    def declare_subscriber(
        self, topic: str, msgtype: str | None, callback: Callback, direct: bool = False
    ) -> Any:
        return self.session.declare_subscriber(self.key(topic, msgtype), handler(callback, direct))

    def discover(self, timeout_s: float = 2.0) -> dict[str, str]:
        """``{topic: type}`` of the publishers announced on the network."""
        from tagtrail.stream.record import discover

        return discover(self.session, timeout_s)

    def close(self) -> None:
        """Withdraw what :meth:`declare_node` announced."""

    def summary(self) -> dict[str, Any]:
        return {}


class RmwPublisher:
    """A zenoh publisher that attaches rmw_zenoh's attachment to every put, with its token."""

    def __init__(self, publisher: zenoh.Publisher, token: Any, gid: bytes) -> None:
        self.publisher = publisher
        self.token = token
        self.gid = gid
        self._seq = itertools.count(1)
        self._lock = threading.Lock()

    @property
    def matching_status(self) -> Any:
        return self.publisher.matching_status

    def put(self, payload: bytes | zenoh.ZBytes) -> None:
        with self._lock:  # sequence numbers leave in order
            self.publisher.put(
                payload, attachment=attachment(next(self._seq), time.time_ns(), self.gid)
            )

    def undeclare(self) -> None:
        try:
            self.token.undeclare()
        finally:
            self.publisher.undeclare()  # type: ignore[no-untyped-call]


class _Entity:
    """A subscriber with its liveliness token (or a second subscriber): undeclared together."""

    def __init__(self, entity: Any, token: Any) -> None:
        self.entity = entity
        self.token = token

    def undeclare(self) -> None:
        try:
            self.token.undeclare()
        finally:
            self.entity.undeclare()


class RmwZenohWire(Wire):
    """The ``rmw_zenoh`` wire (module docstring): ``distro`` sets the type hashes,
    ``domain_id`` the first key chunk; the node is ``/<node>`` (enclave and namespace ``/``)."""

    name = "rmw_zenoh"

    def __init__(self, session: zenoh.Session, distro: str = "humble", domain_id: int = 0) -> None:
        super().__init__(session)
        self.distro = check_distro(distro)
        if domain_id < 0:
            raise SpecError(f"--domain-id {domain_id}: must be >= 0")
        self.domain_id = domain_id
        self.zid = str(session.info.zid())
        self.node: str | None = None
        self._node_token: Any = None
        self._ids = itertools.count(1)  # entity ids; the node is 0, as rmw_zenoh numbers them
        self._last_seq: dict[bytes, int] = {}
        self._lock = threading.Lock()

    def key(self, topic: str, msgtype: str | None = None) -> str:
        name = Wire.key(self, topic)
        if msgtype is None or msgtype == JSON:
            return name if msgtype == JSON else f"{self.domain_id}/{name}/*/*"
        return f"{self.domain_id}/{name}/{dds_type(msgtype)}/{type_hash(msgtype, self.distro)}"

    def token(
        self,
        kind: str,
        eid: int | None = None,
        topic: str | None = None,
        msgtype: str | None = None,
        qos: QoS = DEFAULT_QOS,
    ) -> str:
        """The liveliness token of this node (``NN``) or of one of its endpoints."""
        node = self.node or "tagtrail"
        head = (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/0/{0 if eid is None else eid}/{kind}/"
            f"%/%/{mangle(node)}"
        )
        if topic is None or msgtype is None:
            return head
        name = "/" + topic.strip("/")
        return (
            f"{head}/{mangle(name)}/{dds_type(msgtype)}/{type_hash(msgtype, self.distro)}/"
            f"{qos_string(qos)}"
        )

    def declare_node(self, name: str) -> None:
        if self._node_token is None:
            self.node = name
            self._node_token = self.session.liveliness().declare_token(self.token("NN"))

    def declare_publisher(self, topic: str, msgtype: str | None, **options: Any) -> Any:
        if msgtype is None:
            raise SpecError(f"{topic}: the rmw_zenoh wire needs the message type to publish")
        if msgtype == JSON:
            return self.session.declare_publisher(self.key(topic, msgtype), **options)
        token = self.token("MP", next(self._ids), topic, msgtype)
        pub = self.session.declare_publisher(self.key(topic, msgtype), **options)
        return RmwPublisher(pub, self.session.liveliness().declare_token(token), gid_of(token))

    def declare_subscriber(
        self, topic: str, msgtype: str | None, callback: Callback, direct: bool = False
    ) -> Any:
        """Subscribe to ``topic`` of ``msgtype`` with any type hash (a definition that differs
        from the robot's must not silence a topic: the first message is checked against its
        type where it matters, e.g. by ``stream record``); ``msgtype`` None: any type."""
        key = self.key(topic, msgtype)
        if msgtype is not None and msgtype != JSON:
            key = key.rsplit("/", 1)[0] + "/*"
        if msgtype == JSON:
            return self.session.declare_subscriber(key, handler(callback, direct))
        expect = key.count("/") if "*" in key else None

        def on_sample(sample: zenoh.Sample) -> None:
            if expect is not None and str(sample.key_expr).count("/") != expect:
                return  # `0/a/*/*` (any type) also matches topic /a/b's `0/a/b/<type>`
            self._check(sample.attachment)
            callback(sample)

        sub = self.session.declare_subscriber(key, handler(on_sample, direct))
        if msgtype is None:  # any type (echo): a JSON document on the bare key too
            bare = self.session.declare_subscriber(self.key(topic, JSON), handler(callback, direct))
            return _Entity(sub, bare)
        token = self.session.liveliness().declare_token(
            self.token("MS", next(self._ids), topic, msgtype)
        )
        return _Entity(sub, token)

    def _check(self, att: zenoh.ZBytes | None) -> None:
        if att is None:
            self.counts["without_attachment"] += 1
            return
        try:
            seq, _, gid = parse_attachment(att.to_bytes())
        except ValueError:
            self.counts["bad_attachment"] += 1
            return
        with self._lock:
            last = self._last_seq.get(gid)
            if last is not None and seq != last + 1:
                self.counts["sequence_gaps"] += 1
            self._last_seq[gid] = seq

    def discover(self, timeout_s: float = 2.0) -> dict[str, str]:
        """``{topic: ROS type}`` of the publishers whose ``MP`` tokens are alive in this domain
        (topics of types the shared typestore lacks are left out, logged)."""
        from tagtrail.stream.record import SKIP_TOPICS, normalize_type

        found: dict[str, str] = {}
        try:
            replies = self.session.liveliness().get(
                f"{ADMIN_SPACE}/{self.domain_id}/**", timeout=timeout_s
            )
        except zenoh.ZError as err:
            log.debug("liveliness get: %s", err)
            return found
        for reply in replies:
            ok = getattr(reply, "ok", None)
            ep = parse_token(str(ok.key_expr)) if ok is not None else None
            if ep is None or ep.kind != "MP" or ep.topic is None or ep.dds_type is None:
                continue
            if ep.zid == self.zid or ep.topic in SKIP_TOPICS:
                continue
            try:
                found[ep.topic] = normalize_type(ros_type(ep.dds_type))
            except (ValueError, SpecError):
                log.warning(
                    "record: %s has type %s, unknown here; not recorded", ep.topic, ep.dds_type
                )
        return dict(sorted(found.items()))

    def close(self) -> None:
        if self._node_token is not None:
            try:
                self._node_token.undeclare()
            except Exception as err:  # noqa: BLE001 - shutdown goes on
                log.debug("undeclare node token: %s", err)
            self._node_token = None

    def summary(self) -> dict[str, Any]:
        return {
            "wire": self.name,
            "ros_distro": self.distro,
            "domain_id": self.domain_id,
            "without_attachment": self.counts["without_attachment"],
            "bad_attachment": self.counts["bad_attachment"],
            "sequence_gaps": self.counts["sequence_gaps"],
        }


def make_wire(
    name: str, session: zenoh.Session, distro: str = "humble", domain_id: int = 0
) -> Wire:
    """The wire called ``name`` (:data:`WIRES`) on ``session``."""
    if name == "bridge":
        return Wire(session)
    if name == "rmw_zenoh":
        return RmwZenohWire(session, distro, domain_id)
    raise SpecError(f"--wire {name!r}: use one of {', '.join(WIRES)}")


def wire_from_args(ns: Any, session: zenoh.Session, node: str) -> Wire:
    """The wire of a command's ``--wire/--ros-distro/--domain-id``, its node announced."""
    wire = make_wire(
        getattr(ns, "wire", "bridge"),
        session,
        getattr(ns, "ros_distro", None) or default_distro(),
        default_domain() if getattr(ns, "domain_id", None) is None else ns.domain_id,
    )
    wire.declare_node(node)
    return wire


def default_distro() -> str:
    """``ROS_DISTRO`` when it names a known distro, else humble."""
    env = os.environ.get("ROS_DISTRO", "").strip().lower()
    return env if env in DISTROS else "humble"


def default_domain() -> int:
    """``ROS_DOMAIN_ID`` (an integer >= 0), else 0."""
    env = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return int(env) if env.isdigit() else 0

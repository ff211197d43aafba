"""zenoh sessions for the live nodes: explicit endpoints, no scouting, clean shutdown.

Every session tagtrail opens is configured here. Scouting (multicast and gossip) is off unless
asked for, so a node only talks to the endpoints it is given (``--listen`` / ``--connect``); the
defaults keep everything on the loopback interface: a node that is given no endpoint at all
listens on (relocalize) or connects to (replay, localize) ``tcp/127.0.0.1:7447``. To reach a
robot running zenoh-bridge-ros2dds: ``--connect tcp/<robot-ip>:7447``. With ``--wire rmw_zenoh``
and no endpoint, a node follows rmw_zenoh's topology instead: it connects to the router
``rmw_zenohd`` at ``tcp/localhost:7447`` (gossip scouting on, as rmw_zenoh's peers have it);
from a laptop: ``--mode client --connect tcp/<robot-ip>:7447``.

Publishing follows NOTES "zenoh 1.10": payloads are ``bytes``, keys have no leading ``/``,
publishers wait for their matching status before the first sample, and shutdown undeclares
every entity before closing the session.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from types import FrameType
from typing import Any, NoReturn

import zenoh

from tagtrail.errors import SessionError, SpecError

log = logging.getLogger("tagtrail.stream")
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
MODES = ("peer", "client")


def endpoint(text: str) -> str:
    """``host:port`` → ``tcp/host:port``; a locator with a protocol is kept as it is."""
    text = text.strip()
    if not text:
        raise SpecError("empty zenoh endpoint")
    return text if "/" in text else f"tcp/{text}"


def make_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    scouting: bool = False,
    gossip: bool | None = None,
    low_latency: bool = False,
) -> zenoh.Config:
    """A zenoh config: ``mode`` (peer | client), explicit endpoints, scouting off by default.

    zenoh's own defaults listen on every interface and scout by multicast; both are replaced:
    with ``listen`` empty the session listens nowhere (it only connects out). ``gossip``
    (default: as ``scouting``): gossip scouting alone, as rmw_zenoh's sessions use it to learn
    their peers from the router. ``low_latency``: zenoh's low-latency transport, which writes
    each sample to the socket from the publishing thread (no hand-over to its transmit task:
    through the closed loop's three nodes ~0.1-0.4 ms less, bench/FOLLOW.md). A link uses it
    only when both ends ask for it; it has no priority lanes and does not fragment: a sample
    over its batch (64 KiB) is not for it (measured with zenoh 1.x here: the first such sample
    on a link was lost).
    """
    if mode not in MODES:
        raise SpecError(f"zenoh mode {mode!r}: use one of {', '.join(MODES)}")
    if mode == "client" and not connect:
        raise SpecError("a zenoh client needs --connect ENDPOINT (a router or peer to join)")
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    if low_latency:  # zenoh requires its QoS lanes off for it
        cfg.insert_json5("transport/unicast/lowlatency", "true")
        cfg.insert_json5("transport/unicast/qos/enabled", "false")
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(scouting)))
    cfg.insert_json5(
        "scouting/gossip/enabled", json.dumps(bool(scouting if gossip is None else gossip))
    )
    if mode == "peer":
        cfg.insert_json5("listen/endpoints", json.dumps([endpoint(e) for e in listen]))
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint(e) for e in connect]))
    return cfg


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """``--mode``, ``--listen``, ``--connect``, ``--scouting`` (shared by every stream command)."""
    g = parser.add_argument_group("zenoh session")
    g.add_argument("--mode", choices=MODES, default="peer", help="zenoh mode (default: peer)")
    g.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    g.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)",
    )
    g.add_argument(
        "--scouting",
        action="store_true",
        help="enable multicast/gossip scouting (off by default: explicit endpoints)",
    )
    add_wire_arguments(parser)


def add_wire_arguments(parser: argparse.ArgumentParser) -> None:
    """``--wire``, ``--ros-distro``, ``--domain-id`` (:mod:`tagtrail.stream.wire`)."""
    from tagtrail.stream.wire import DISTROS, WIRES

    g = parser.add_argument_group("wire")
    g.add_argument(
        "--wire",
        choices=WIRES,
        default="bridge",
        help="bridge: zenoh-bridge-ros2dds keys (default); rmw_zenoh: the keys, "
        "attachments and liveliness tokens of ROS 2's rmw_zenoh_cpp (no bridge)",
    )
    g.add_argument(
        "--ros-distro",
        choices=DISTROS,
        default=None,
        help="rmw_zenoh: the robot's ROS 2 distro, which sets the type hashes in "
        "the keys (default: $ROS_DISTRO, else humble)",
    )
    g.add_argument(
        "--domain-id",
        type=_domain_id,
        default=None,
        metavar="N",
        help="rmw_zenoh: ROS_DOMAIN_ID of the robot (default: $ROS_DOMAIN_ID, else 0)",
    )


def _domain_id(text: str) -> int:
    if not text.strip().isdigit():
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return int(text)


def config_from_args(ns: argparse.Namespace, default_role: str) -> zenoh.Config:
    """The session config of a command; ``default_role`` (listen | connect) applies the default
    endpoint when neither ``--listen`` nor ``--connect`` is given."""
    listen, connect = list(ns.listen), list(ns.connect)
    fast = getattr(ns, "low_latency", False)  # the controller chain's nodes have --low-latency
    if getattr(ns, "wire", "bridge") == "rmw_zenoh" and not listen and not connect:
        # rmw_zenoh's topology (design.md): a peer that connects to the router on this
        # machine, listens on the loopback and learns the other peers by gossip from the router
        from tagtrail.stream.wire import RMW_ROUTER

        return make_config(
            ns.mode,
            ["tcp/localhost:0"] if ns.mode == "peer" else [],
            [RMW_ROUTER],
            ns.scouting,
            gossip=True,
            low_latency=fast,
        )
    if not listen and not connect and not ns.scouting:
        (listen if default_role == "listen" and ns.mode == "peer" else connect).append(
            DEFAULT_ENDPOINT
        )
    return make_config(ns.mode, listen, connect, ns.scouting, low_latency=fast)


def open_session(cfg: zenoh.Config) -> zenoh.Session:
    """Open a session; a failure (port in use, bad locator) becomes one :class:`SessionError`."""
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as err:
        ends = {k: cfg.get_json(f"{k}/endpoints") for k in ("listen", "connect")}
        raise SessionError(f"cannot open the zenoh session ({ends}): {err}") from err


def close_all(
    session: zenoh.Session | None, entities: Sequence[Any], timeout_s: float = 0.5
) -> bool:
    """Undeclare publishers/subscribers/queryables (never raising), then close the session,
    waiting at most ``timeout_s`` for it. True if the session is closed (or there is none).

    ``session.close()`` can take zenoh's full congestion timeout (5 s, a put blocked by a
    congested link) or its close timeout (10 s); a node must stop in well under a second, so the
    close goes on in a daemon thread past the deadline.
    """
    for e in reversed(entities):
        try:
            e.undeclare()
        except Exception as err:  # noqa: BLE001 - shutdown must go on
            log.debug("undeclare %r: %s", e, err)
    if session is None or session.is_closed():
        return True

    def close() -> None:
        try:
            session.close()  # type: ignore[no-untyped-call]  # unannotated in zenoh's stubs
        except Exception as err:  # noqa: BLE001
            log.debug("session close: %s", err)

    worker = threading.Thread(target=close, name="zenoh close", daemon=True)
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        log.warning(
            "zenoh session still closing after %.1f s (a congested link); not waiting", timeout_s
        )
        return False
    return True


def matching(publisher: zenoh.Publisher) -> bool:
    """Whether ``publisher`` has a matching subscriber now.

    In eclipse-zenoh 1.x ``matching_status`` is a ``MatchingStatus`` object, always truthy: the
    answer is its ``.matching`` field.
    """
    # zenoh's stubs declare ``-> bool``; at run time it is the MatchingStatus above
    return bool(publisher.matching_status.matching)  # type: ignore[attr-defined]


def wait_matching(publisher: zenoh.Publisher, timeout_s: float, stop: threading.Event) -> bool:
    """Wait until ``publisher`` has a matching subscriber (or timeout/stop); True if matched."""
    deadline = time.monotonic() + timeout_s
    while not matching(publisher):
        if stop.is_set() or time.monotonic() >= deadline:
            return False
        stop.wait(min(0.01, max(deadline - time.monotonic(), 0.0)))
    return True


def leave_now(code: int) -> NoReturn:
    """Flush stdout/stderr and end the process at once with ``code``.

    For a node whose shutdown was not clean: zenoh runs callbacks in non-daemon threads, and one
    blocked in a congested reliable put would hold the interpreter's exit for up to 5 s.
    """
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT/SIGTERM while the block runs (handlers restored after).

    Off the main thread (signals cannot be handled there) the event is only set by the caller.
    """
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum: int, _frame: FrameType | None) -> None:
        log.info("%s: shutting down", signal.Signals(signum).name)
        stop.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)

"""The live nodes' outputs on a Foxglove WebSocket (``--foxglove [PORT]``): Foxglove without ROS.

Served by Foxglove's own SDK (``foxglove-sdk``, ``pip install 'tagtrail[foxglove]'``; its Rust
server speaks the WebSocket subprotocol ``foxglove.sdk.v1``): nothing of the protocol is written
here. Each output key ``<prefix>/<name>`` becomes the channel ``/<prefix>/<name>`` carrying the
very bytes published on zenoh: CDR (``cdr`` message encoding) with the ROS 2 message definition
from rosbags' type store as a ``ros2msg`` schema, so Foxglove decodes them as it decodes a ROS 2
bag; the relocalization ``state`` is a JSON channel. The server binds 127.0.0.1 unless told
otherwise (``--foxglove-host``). Latched payloads (the reference path and its marker) are sent
again whenever a client subscribes to their channel, so a late client sees them even with
``--path-period 0``. What a user does and sees: docs/FOXGLOVE.md.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from tagtrail.errors import SessionError, SpecError, one_line
from tagtrail.io import msgs
from tagtrail.stream.stats import say

log = logging.getLogger("tagtrail.stream")
Handler = Callable[[bytes], Iterable[tuple[str, bytes]]]  # a node's (tagtrail.stream.node)
DEFAULT_PORT = 8765
FOXGLOVE_MISSING = "--foxglove needs the foxglove-sdk package: pip install 'tagtrail[foxglove]'"
JSON_TYPE = "json"  # a key whose payload is JSON text, not CDR
STATE_SCHEMA = {
    "type": "object",
    "title": "tagtrail relocalization state",
    "properties": {
        k: {"type": t}
        for k, t in (
            ("stamp_sec", "integer"),
            ("stamp_nanosec", "integer"),
            ("distance_m", "number"),
            ("heading_error_deg", "number"),
            ("heading_error_rad", "number"),
            ("nearest_ref_idx", "integer"),
            ("u", "number"),
            ("v", "number"),
        )
    },
}


def load_sdk() -> Any:
    """The ``foxglove`` module; a one-line :class:`SpecError` saying what to install if absent."""
    try:
        return importlib.import_module("foxglove")
    except ImportError as err:
        raise SpecError(FOXGLOVE_MISSING) from err


def ros2_schema(typename: str) -> tuple[str, bytes]:
    """``(schema name, ros2msg text)`` of a ROS 2 type, e.g. ``std_msgs/msg/Float64``: the full
    definition with its dependencies, as rosbag2 stores it in an MCAP file."""
    text, _ = msgs.typestore().generate_msgdef(typename, ros_version=2)
    return typename, text.encode()


class FoxgloveServer:
    """A Foxglove WebSocket server with one channel per output key.

    ``types``: key → ROS 2 type name (or :data:`JSON_TYPE`). ``port`` 0 picks a free one
    (:attr:`port` says which).
    """

    def __init__(
        self,
        types: dict[str, str],
        port: int = DEFAULT_PORT,
        host: str = "127.0.0.1",
        name: str = "tagtrail",
    ) -> None:
        fg = load_sdk()
        self._fg = fg
        self._ctx = fg.Context()
        self._channels: dict[str, Any] = {}
        for key, typename in types.items():
            topic = "/" + key
            if typename == JSON_TYPE:
                ch = fg.Channel(topic, schema=STATE_SCHEMA, context=self._ctx)
            else:
                sname, data = ros2_schema(typename)
                ch = fg.Channel(
                    topic,
                    schema=fg.Schema(name=sname, encoding="ros2msg", data=data),
                    message_encoding="cdr",
                    context=self._ctx,
                )
            self._channels[key] = ch
        self._latched: dict[str, list[bytes]] = {}  # channel topic → payloads
        self._lock = threading.Lock()
        listener = _listener(importlib.import_module("foxglove.websocket"), self._on_subscribe)
        try:
            self.server = fg.start_server(
                name=name, host=host, port=port, context=self._ctx, server_listener=listener
            )
        except Exception as err:  # the SDK raises its own (Rust) error types
            why = one_line(err)
            raise SessionError(f"--foxglove: cannot serve on {host}:{port}: {why}") from err
        self.port: int = int(self.server.port)
        self.host = host

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def log(self, key: str, payload: bytes, t_ns: int | None = None) -> None:
        """Send one payload on ``key``'s channel (log time: now unless ``t_ns``)."""
        ch = self._channels.get(key)
        if ch is not None:
            ch.log(payload, log_time=time.time_ns() if t_ns is None else t_ns)

    def latch(self, outputs: Iterable[tuple[str, bytes]]) -> None:
        """Send ``outputs`` now and again to each client that subscribes later (replacing what
        was latched on their keys before)."""
        fresh: dict[str, list[bytes]] = {}
        for key, payload in outputs:
            fresh.setdefault("/" + key, []).append(payload)
            self.log(key, payload)
        with self._lock:
            self._latched.update(fresh)

    def tee(self, outputs: Iterable[tuple[str, bytes]]) -> Iterator[tuple[str, bytes]]:
        """``outputs`` unchanged, each also sent on its channel as it passes."""
        for key, payload in outputs:
            self.log(key, payload)
            yield key, payload

    def _on_subscribe(self, topic: str) -> None:
        with self._lock:
            payloads = list(self._latched.get(topic, ()))
        for payload in payloads:
            self.log(topic[1:], payload)

    def close(self) -> None:
        """Stop the server (idempotent)."""
        server, self.server = self.server, None
        if server is not None:
            server.stop()


def _listener(ws: Any, on_subscribe: Callable[[str], None]) -> Any:
    """A ``foxglove.websocket.ServerListener`` (the SDK's protocol class, whose other callbacks
    do nothing) that calls ``on_subscribe(channel topic)``."""

    class Listener(ws.ServerListener):  # type: ignore[misc]
        def on_subscribe(self, client: Any, channel: Any) -> None:
            try:
                on_subscribe(str(channel.topic))
            except Exception as err:  # noqa: BLE001 - a callback must never kill the server
                log.warning("foxglove: on subscribe to %s: %s", channel.topic, err)

    return Listener()


def foxglove_server(
    ns: argparse.Namespace, node: str, types: dict[str, str]
) -> FoxgloveServer | None:
    """The server ``--foxglove [PORT]`` / ``--foxglove-host`` ask for (None without the flag), a
    channel per key of ``types`` (key → ROS 2 type or :data:`JSON_TYPE`); its URL is printed as
    ``<node>: foxglove ws://HOST:PORT``."""
    if getattr(ns, "foxglove", None) is None:
        return None
    fox = FoxgloveServer(types, ns.foxglove, ns.foxglove_host, name=f"tagtrail {node}")
    say(f"{node}: foxglove {fox.url}")
    return fox


def teed(fox: FoxgloveServer | None, handler: Handler) -> Handler:
    """``handler`` whose outputs also go to ``fox`` (``handler`` itself without a server)."""
    if fox is None:
        return handler
    return lambda data: fox.tee(handler(data))

"""``tagtrail stream relocalize | replay | localize``: the live nodes over eclipse-zenoh.

Thin shell: parse → load (files are read before any port is opened) → open the session → run
the node until SIGINT/SIGTERM, ``--duration`` or ``--count`` → close → exit code. Runs standalone
too: ``python -m tagtrail.stream.cli relocalize …``.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tagtrail.geometry.reference_path import PLANES
from tagtrail.stream.codec import POSE_TYPES
from tagtrail.stream.session import add_session_arguments, config_from_args, open_session

EXAMPLES = """examples:
  tagtrail stream relocalize --reference outputs/reference --alignment reloc/summary.json
  tagtrail stream relocalize --reference outputs/query_1 --pipeline lab.yaml --dataset query_1
  tagtrail stream relocalize --reference ref/trajetoria_camera.csv --plane xz \\
      --connect tcp/192.168.1.10:7447          # the robot's zenoh-bridge-ros2dds
  tagtrail stream replay outputs/query/trajectory.csv --rate 2
  tagtrail stream replay recording/ --topics /detections /camera_info
  tagtrail stream localize --map outputs/reference/tag_map.yaml
"""


def _number(kind: type, low: float, strict: bool = False) -> Callable[[str], Any]:
    """An argparse ``type=``: a finite ``kind`` (int or float) ≥ ``low`` (> ``low`` if
    ``strict``); anything else is one argparse error line (exit 2)."""
    bound = f"{'>' if strict else '>='} {low:g}"
    what = "an integer" if kind is int else "a number"
    must = "an integer" if kind is int else "a finite number"

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if not math.isfinite(value) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"must be {must} {bound}, got {text!r}")
        return value
    return parse


NON_NEGATIVE = _number(float, 0.0)  # durations, periods, rates, margins
COUNT = _number(int, 0)
POSITIVE = _number(float, 0.0, strict=True)


def tcp_port(text: str) -> int:
    """An argparse ``type=``: a TCP port 0..65535 (0: any free one)."""
    port = COUNT(text)
    if port > 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port 0..65535, got {text!r}")
    return int(port)


def _pipeline(p: argparse.ArgumentParser, what: str) -> None:
    g = p.add_argument_group("parameters")
    g.add_argument("--pipeline", type=Path, default=None, metavar="FILE",
                   help=f"take {what} from this pipeline file (default: ./pipeline.yaml if there "
                   "is one, else the stages' defaults); flags below override it")
    g.add_argument("--dataset", default=None, metavar="NAME",
                   help="whose parameters (its `params:` applied; default: the reference)")


def _common(p: argparse.ArgumentParser, count_help: str, express: bool) -> None:
    add_session_arguments(p)
    g = p.add_argument_group("run")
    g.add_argument("--duration", type=NON_NEGATIVE, default=None, metavar="S",
                   help="stop after S seconds (default: run until SIGINT/SIGTERM)")
    g.add_argument("--count", type=COUNT, default=None, metavar="N", help=count_help)
    g.add_argument("--congestion", choices=["block", "drop"], default="block",
                   help="when the network is congested: block (reliable, default) or drop")
    g.add_argument("--express", action=argparse.BooleanOptionalAction, default=express,
                   help="send every sample at once, no batching (default: "
                   f"{'on: lowest latency for a controller' if express else 'off'})")
    g.add_argument("--stats-period", type=NON_NEGATIVE, default=10.0, metavar="S",
                   help="log a stats line every S seconds (0: never; default 10)")


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``relocalize``, ``replay`` and ``localize`` sub-commands to ``parser``."""
    parser.epilog = EXAMPLES
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    sub = parser.add_subparsers(dest="stream_command", metavar="COMMAND")
    fmt = argparse.RawDescriptionHelpFormatter

    p = sub.add_parser("relocalize", help="live D and phi of incoming poses", epilog=EXAMPLES,
                       formatter_class=fmt, description="Subscribe to live poses, publish D, "
                       "phi, poses, the reference path and RViz markers (SPEC Streaming).")
    p.add_argument("--reference", type=Path, required=True,
                   help="reference trajectory (folder or file, tagtrail's or the original layout)")
    p.add_argument("--alignment", type=Path, default=None,
                   help="summary.json of `tagtrail relocalize`, an align-stage alignment JSON, "
                   "or JSON with a 4x4 'ref_A_query' (default: poses are in the reference frame)")
    p.add_argument("--pose-key", default="tag_only_pose", help="input key (default: %(default)s)")
    p.add_argument("--pose-type", choices=list(POSE_TYPES), default="pose_stamped",
                   help="input message type (default: %(default)s)")
    p.add_argument("--prefix", default="relocalization", help="output key prefix (default: "
                   "%(default)s)")
    p.add_argument("--plane", choices=list(PLANES), default=None,
                   help="plane of D and phi (default: the alignment file's, else the pipeline's "
                   "report.plane)")
    p.add_argument("--frame-id", default="map", help="frame of the outputs (default: map)")
    p.add_argument("--path-period", type=NON_NEGATIVE, default=1.0, metavar="S",
                   help="republish the reference path every S seconds (0: once; default 1)")
    p.add_argument("--path-max-points", type=COUNT, default=10_000, metavar="N",
                   help="decimate the published path to N poses (0: all; default 10000)")
    _pipeline(p, "report's plane")
    _common(p, "stop after N input messages", express=True)
    g = p.add_argument_group("foxglove")
    g.add_argument("--foxglove", type=tcp_port, nargs="?", const=8765, default=None,
                   metavar="PORT",
                   help="also serve the outputs on a Foxglove WebSocket (default port 8765; "
                   "pip install 'tagtrail[foxglove]')")
    g.add_argument("--foxglove-host", default="127.0.0.1", metavar="HOST",
                   help="address the Foxglove server binds (default: %(default)s, this machine "
                   "only; 0.0.0.0: every interface)")

    p = sub.add_parser("replay", help="publish a trajectory's poses (or bag topics)",
                       epilog=EXAMPLES, formatter_class=fmt,
                       description="Publish the poses of a trajectory file or a bag's pose topic "
                       "as CDR PoseStamped, at the recorded rate.")
    p.add_argument("source", type=Path, help="trajectory CSV/TUM/folder, or a bag")
    p.add_argument("--rate", type=NON_NEGATIVE, default=1.0,
                   help="speed factor, >= 0 (0: as fast as possible; default 1)")
    p.add_argument("--key", default="tag_only_pose", help="output key (default: %(default)s)")
    p.add_argument("--topic", default=None, help="the bag's pose topic (default: the only one)")
    p.add_argument("--topics", nargs="+", default=None, metavar="TOPIC",
                   help="publish these bag topics unchanged, key = topic without '/'")
    p.add_argument("--frame-id", default=None, help="frame of the poses (default: the bag's, "
                   "map for trajectory files)")
    p.add_argument("--wait", type=NON_NEGATIVE, default=10.0, metavar="S",
                   help="wait up to S seconds for a subscriber on every key (default 10); "
                   "if a key has none by then: exit 2, nothing published")
    p.add_argument("--publish-anyway", action="store_true",
                   help="publish even if a key has no subscriber after --wait (a warning)")
    _common(p, "publish at most N messages", express=False)

    p = sub.add_parser("localize", help="live world_T_cam from detections or images",
                       epilog=EXAMPLES, formatter_class=fmt,
                       description="Camera pose from apriltag detections (or compressed images) "
                       "and the tag map, published as PoseStamped.")
    p.add_argument("--map", type=Path, required=True, help="tag_map.yaml / tag_map.csv / folder")
    p.add_argument("--detections-key", default="detections", help="default: %(default)s")
    p.add_argument("--camera-info-key", default="camera_info", help="default: %(default)s")
    p.add_argument("--image-key", default=None,
                   help="detect tags in images on this key instead of using detections")
    p.add_argument("--image-type", choices=["compressed", "raw"], default="compressed")
    p.add_argument("--pose-key", default="tag_only_pose", help="output key (default: "
                   "%(default)s)")
    p.add_argument("--frame-id", default="map", help="frame of the poses (default: map)")
    _pipeline(p, "extract's detector and filters, pnp's tag sizes and trajectory's method")
    g = p.add_argument_group("overrides")
    g.add_argument("--tag-size", type=POSITIVE, default=None, metavar="M",
                   help="edge (m) of tags whose size neither the map nor pnp.tag_sizes gives "
                   "(default: pnp.tag_size)")
    g.add_argument("--method", choices=["auto", "avg", "lsq", "pnp"], default=None,
                   help="per-frame method (default: trajectory.method)")
    g.add_argument("--min-decision-margin", type=NON_NEGATIVE, default=None, metavar="M",
                   help="drop detections with a lower decision margin (default: "
                   "extract.min_decision_margin)")
    g.add_argument("--max-hamming", type=COUNT, default=None, metavar="N",
                   help="drop detections with more corrected bits (default: extract.max_hamming)")
    _common(p, "stop after N input messages", express=True)
    return parser


def build_parser() -> argparse.ArgumentParser:
    return add_arguments(argparse.ArgumentParser(prog="tagtrail stream",
                                                 description="Live nodes over eclipse-zenoh."))


def main(args: argparse.Namespace | Sequence[str] | None = None) -> int:
    """Run a stream command from parsed arguments (or an argv list); 0 on success."""
    from tagtrail.cli import run_command

    ns = args if isinstance(args, argparse.Namespace) else build_parser().parse_args(args)
    cmd = getattr(ns, "stream_command", None)
    if cmd is None:
        build_parser().print_help()
        return 2
    run = {"relocalize": _relocalize, "replay": _replay, "localize": _localize}[cmd]
    return run_command(lambda: run(ns))


def _relocalize(ns: argparse.Namespace) -> int:
    from tagtrail.io.layouts import read_trajectory
    from tagtrail.stages import report as report_stage
    from tagtrail.stream.params import stage_params
    from tagtrail.stream.reloc_node import Relocalizer, load_alignment, serve
    from tagtrail.stream.session import leave_now, stop_on_signals

    ref = read_trajectory(ns.reference)
    # the alignment file's plane wins over the pipeline's: its planar transform acts in that plane
    plane = ns.plane
    if not plane:
        report = stage_params(["report"], ns.pipeline, ns.dataset)["report"]
        assert isinstance(report, report_stage.Params)
        plane = report.plane
    alignment = None
    if ns.alignment is not None:
        A, R, file_plane = load_alignment(ns.alignment, ref, plane)
        alignment, plane = (A, R), ns.plane or file_plane or plane
    reloc = Relocalizer(ref, plane, alignment, ns.frame_id, ns.prefix, ns.pose_type,
                        ns.path_max_points)  # fmt: skip
    fox = None
    if getattr(ns, "foxglove", None) is not None:
        from tagtrail.stream.reloc_node import foxglove_server

        fox = foxglove_server(reloc, ns.foxglove, ns.foxglove_host)
        print(f"relocalize: foxglove {fox.url}", flush=True)
    try:
        session = open_session(config_from_args(ns, "listen"))
    except BaseException:
        if fox is not None:
            fox.close()
        raise
    with stop_on_signals() as stop:
        summary = serve(reloc, session, ns.pose_key, congestion=ns.congestion,
                        express=ns.express, path_period_s=ns.path_period,
                        duration_s=ns.duration, count=ns.count,
                        stats_period_s=ns.stats_period, stop=stop, foxglove=fox)  # fmt: skip
    if not summary["shutdown_clean"]:
        leave_now(0)  # a zenoh callback thread blocked in a put would hold the exit for 5 s
    return 0


def _replay(ns: argparse.Namespace) -> int:
    from tagtrail.stream.replay import Replayed, bag_messages, load_poses, pose_messages, replay
    from tagtrail.stream.session import close_all, leave_now, stop_on_signals

    if ns.topics:
        messages = bag_messages(ns.source, ns.topics)
    else:
        messages = pose_messages(load_poses(ns.source, ns.topic, ns.frame_id), ns.key)
    session = open_session(config_from_args(ns, "connect"))
    done = Replayed(0)
    try:
        with stop_on_signals() as stop:
            done = replay(session, messages, rate=ns.rate, count=ns.count, wait_s=ns.wait,
                          publish_anyway=ns.publish_anyway, congestion=ns.congestion,
                          express=ns.express, stop=stop)  # fmt: skip
    finally:
        closed = close_all(session, [], timeout_s=0.5 if done.clean else 0.1)
    if not (done.clean and closed):
        leave_now(0)  # the put blocked by a congested link would hold the exit for 5 s
    return 0


def localize_params(ns: argparse.Namespace) -> Any:
    """The localize node's :class:`~tagtrail.stream.localize.Params`: the ``--pipeline`` /
    ``--dataset`` parameters (else the stages' defaults) with the flags given applied."""
    from tagtrail.stages import extract, pnp, trajectory
    from tagtrail.stream.localize import Params
    from tagtrail.stream.params import override, stage_params

    got = stage_params(["extract", "pnp", "trajectory"], ns.pipeline, ns.dataset)
    ex, pn, tr = got["extract"], got["pnp"], got["trajectory"]
    assert isinstance(ex, extract.Params) and isinstance(pn, pnp.Params)
    assert isinstance(tr, trajectory.Params)
    return Params(
        extract=override(ex, {
            "min_decision_margin": ("--min-decision-margin", ns.min_decision_margin),
            "max_hamming": ("--max-hamming", ns.max_hamming)}),
        pnp=override(pn, {"tag_size": ("--tag-size", ns.tag_size)}),
        trajectory=override(tr, {"method": ("--method", ns.method)}),
    )  # fmt: skip


def _localize(ns: argparse.Namespace) -> int:
    from tagtrail.io.layouts import read_tag_map
    from tagtrail.stream.localize import Localizer, cv2_threads
    from tagtrail.stream.node import Node
    from tagtrail.stream.session import leave_now, stop_on_signals
    from tagtrail.stream.stats import Stats

    tags, _ = read_tag_map(ns.map)
    stats = Stats("localize")
    loc = Localizer(tags, localize_params(ns), ns.pose_key, ns.frame_id, stats)
    cv2_threads()
    node = Node(open_session(config_from_args(ns, "connect")), stats, ns.congestion, ns.express)
    node.count = ns.count
    try:
        node.publisher(ns.pose_key)
        node.subscribe(ns.camera_info_key, loc.on_camera_info)
        if ns.image_key:
            node.subscribe(ns.image_key, lambda b: loc.on_image(b, ns.image_type),
                           latest_only=True)  # fmt: skip
        else:
            node.subscribe(ns.detections_key, loc.on_detections)
    except BaseException:
        node.close()
        raise
    with stop_on_signals() as stop:
        node.run(ns.duration, ns.stats_period, stop)
    if ns.image_key or not node.clean:
        # pupil-apriltags may segfault in its destructor at interpreter exit (NOTES; upstream
        # pupil-labs/apriltags#46), and a zenoh callback blocked in a put would hold the exit
        # for 5 s: the session is closed (or abandoned) and stats printed, so leave at once
        leave_now(0)
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    sys.exit(main())

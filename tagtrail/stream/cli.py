"""``tagtrail stream relocalize | replay | localize | record | echo | follow``: the live nodes
over eclipse-zenoh.

Thin shell: parse → load (files are read before any port is opened) → open the session → run
the node until SIGINT/SIGTERM, ``--duration`` or ``--count`` → close → exit code. Runs standalone
too: ``python -m tagtrail.stream.cli relocalize …``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tagtrail.errors import SourceError, SpecError
from tagtrail.geometry.reference_path import PLANES
from tagtrail.stream.codec import POSE_TYPES
from tagtrail.stream.session import add_session_arguments, config_from_args, open_session
from tagtrail.stream.stats import say

EXAMPLES = """examples:
  tagtrail stream relocalize --reference outputs/reference --alignment reloc/summary.json
  tagtrail stream relocalize --reference outputs/query_1 --pipeline lab.yaml --dataset query_1
  tagtrail stream relocalize --reference ref/trajetoria_camera.csv --plane xz \\
      --connect tcp/192.168.1.10:7447          # the robot's zenoh-bridge-ros2dds
  tagtrail stream replay outputs/query/trajectory.csv --rate 2
  tagtrail stream replay recording/ --topics /detections /camera_info
  tagtrail stream localize --map outputs/reference/tag_map.yaml
  tagtrail stream relocalize --reference outputs/reference --foxglove   # ws://127.0.0.1:8765
  tagtrail stream localize --profile limo --map outputs/reference/tag_map.yaml
  tagtrail stream record bags/run1 --profile limo --mode client --connect tcp/192.168.1.10:7447
  tagtrail stream follow --profile limo --reference outputs/reference --speed 0.3 \\
      --connect tcp/127.0.0.1:7447 --connect tcp/192.168.1.10:7447   # Twist on /cmd_vel
  tagtrail stream record bags/run1 --topic /camera/color/image_raw:sensor_msgs/msg/Image \\
      --topic /camera/color/camera_info:sensor_msgs/msg/CameraInfo --duration 60
"""
ECHO_EXAMPLES = """examples:
  tagtrail stream echo relocalization/state --count 5
  tagtrail stream echo relocalization/distance_m --connect tcp/192.168.1.10:7447
"""


def _number(kind: type, low: float, strict: bool = False) -> Callable[[str], Any]:
    """An argparse ``type=``: a finite ``kind`` (int or float) ≥ ``low`` (> ``low`` if
    ``strict``); anything else is one argparse error line (exit 2)."""
    bound = f" {'>' if strict else '>='} {low:g}" if math.isfinite(low) else ""
    what = "an integer" if kind is int else "a number"
    must = "an integer" if kind is int else "a finite number"

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if not math.isfinite(value) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"must be {must}{bound}, got {text!r}")
        return value

    return parse


NON_NEGATIVE = _number(float, 0.0)  # durations, periods, rates, margins
COUNT = _number(int, 0)
POSITIVE = _number(float, 0.0, strict=True)
FINITE = _number(float, -math.inf)  # offsets that may be negative


def tcp_port(text: str) -> int:
    """An argparse ``type=``: a TCP port 0..65535 (0: any free one)."""
    port = COUNT(text)
    if port > 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port 0..65535, got {text!r}")
    return int(port)


def _foxglove(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("foxglove")
    g.add_argument(
        "--foxglove",
        type=tcp_port,
        nargs="?",
        const=8765,
        default=None,
        metavar="PORT",
        help="also serve the outputs on a Foxglove WebSocket (foxglove-sdk; default "
        "port 8765; pip install 'tagtrail[foxglove]'; docs/FOXGLOVE.md)",
    )
    g.add_argument(
        "--foxglove-host",
        default="127.0.0.1",
        metavar="HOST",
        help="address the Foxglove server binds (default: %(default)s, this machine "
        "only; 0.0.0.0: every interface)",
    )


def _pipeline(p: argparse.ArgumentParser, what: str) -> None:
    g = p.add_argument_group("parameters")
    g.add_argument(
        "--pipeline",
        type=Path,
        default=None,
        metavar="FILE",
        help=f"take {what} from this pipeline file (default: ./pipeline.yaml if there "
        "is one, else the stages' defaults); flags below override it",
    )
    g.add_argument(
        "--dataset",
        default=None,
        metavar="NAME",
        help="whose parameters (its `params:` applied; default: the reference)",
    )


def _profile(p: argparse.ArgumentParser, what: str) -> None:
    from tagtrail.schemas.profiles import PROFILES

    p.add_argument(
        "--profile",
        choices=list(PROFILES),
        default=None,
        help=f"{what} of a profile (tagtrail init --list-profiles); flags override it",
    )


def _run_group(p: argparse.ArgumentParser) -> Any:
    """The session's arguments and the ``run`` group with ``--duration``."""
    add_session_arguments(p)
    g = p.add_argument_group("run")
    g.add_argument(
        "--duration",
        type=NON_NEGATIVE,
        default=None,
        metavar="S",
        help="stop after S seconds (default: run until SIGINT/SIGTERM)",
    )
    return g


def _common(p: argparse.ArgumentParser, count_help: str, express: bool) -> None:
    g = _run_group(p)
    g.add_argument("--count", type=COUNT, default=None, metavar="N", help=count_help)
    g.add_argument(
        "--congestion",
        choices=["block", "drop"],
        default="block",
        help="when the network is congested: block (reliable, default) or drop",
    )
    g.add_argument(
        "--express",
        action=argparse.BooleanOptionalAction,
        default=express,
        help="send every sample at once, no batching (default: "
        f"{'on: lowest latency for a controller' if express else 'off'})",
    )
    if express:  # the nodes of a controller's chain
        g.add_argument(
            "--low-latency",
            action="store_true",
            help="zenoh's low-latency transport on links to peers that ask for it too: each "
            "sample written at once by the publishing thread (~0.1 ms a hop less), no priority "
            "lanes, no sample over 64 KiB (not for images; default: off)",
        )
    g.add_argument(
        "--stats-period",
        type=NON_NEGATIVE,
        default=10.0,
        metavar="S",
        help="log a stats line every S seconds (0: never; default 10)",
    )


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``relocalize``, ``replay`` and ``localize`` sub-commands to ``parser``."""
    parser.epilog = EXAMPLES
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    sub = parser.add_subparsers(dest="stream_command", metavar="COMMAND")
    fmt = argparse.RawDescriptionHelpFormatter

    p = sub.add_parser(
        "relocalize",
        help="live D and phi of incoming poses",
        epilog=EXAMPLES,
        formatter_class=fmt,
        description="Subscribe to live poses, publish D, "
        "phi, poses, the reference path and RViz markers (SPEC Streaming).",
    )
    p.add_argument(
        "--reference",
        type=Path,
        required=True,
        help="reference trajectory (folder or file, tagtrail's or the original layout)",
    )
    p.add_argument(
        "--alignment",
        type=Path,
        default=None,
        help="summary.json of `tagtrail relocalize`, an align-stage alignment JSON, "
        "or JSON with a 4x4 'ref_A_query' (default: poses are in the reference frame)",
    )
    p.add_argument(
        "--pose-key", default=None, help="input key (default: the profile's, else tag_only_pose)"
    )
    p.add_argument(
        "--pose-type",
        choices=list(POSE_TYPES),
        default="pose_stamped",
        help="input message type (default: %(default)s)",
    )
    p.add_argument(
        "--prefix", default="relocalization", help="output key prefix (default: %(default)s)"
    )
    p.add_argument(
        "--plane",
        choices=list(PLANES),
        default=None,
        help="plane of D and phi (default: the alignment file's, else the pipeline's report.plane)",
    )
    p.add_argument(
        "--association",
        choices=["progress", "nearest"],
        default=None,
        help="progress = the nearest sample near the previous match (no jumps where "
        "the path crosses itself), nearest = the paper's Eq. 3.12 (default: the "
        "pipeline's report.association, else progress)",
    )
    p.add_argument("--frame-id", default="map", help="frame of the outputs (default: map)")
    p.add_argument(
        "--path-period",
        type=NON_NEGATIVE,
        default=1.0,
        metavar="S",
        help="republish the reference path every S seconds (0: once; default 1)",
    )
    p.add_argument(
        "--path-max-points",
        type=COUNT,
        default=10_000,
        metavar="N",
        help="decimate the published path to N poses (0: all; default 10000)",
    )
    _pipeline(p, "report's plane")
    _profile(p, "the pose key and report's plane (without a pipeline file)")
    _common(p, "stop after N input messages", express=True)
    _foxglove(p)

    p = sub.add_parser(
        "replay",
        help="publish a trajectory's poses (or bag topics)",
        epilog=EXAMPLES,
        formatter_class=fmt,
        description="Publish the poses of a trajectory file or a bag's pose topic "
        "as CDR PoseStamped, at the recorded rate.",
    )
    p.add_argument("source", type=Path, help="trajectory CSV/TUM/folder, or a bag")
    p.add_argument(
        "--rate",
        type=NON_NEGATIVE,
        default=1.0,
        help="speed factor, >= 0 (0: as fast as possible; default 1)",
    )
    p.add_argument("--key", default="tag_only_pose", help="output key (default: %(default)s)")
    p.add_argument("--topic", default=None, help="the bag's pose topic (default: the only one)")
    p.add_argument(
        "--topics",
        nargs="+",
        default=None,
        metavar="TOPIC",
        help="publish these bag topics unchanged, key = topic without '/'",
    )
    _profile(p, "--topics: the recorded topics")
    p.add_argument(
        "--frame-id",
        default=None,
        help="frame of the poses (default: the bag's, map for trajectory files)",
    )
    p.add_argument(
        "--wait",
        type=NON_NEGATIVE,
        default=10.0,
        metavar="S",
        help="wait up to S seconds for a subscriber on every key (default 10); "
        "if a key has none by then: exit 2, nothing published",
    )
    p.add_argument(
        "--publish-anyway",
        action="store_true",
        help="publish even if a key has no subscriber after --wait (a warning)",
    )
    _common(p, "publish at most N messages", express=False)

    p = sub.add_parser(
        "localize",
        help="live world_T_cam from detections or images",
        epilog=EXAMPLES,
        formatter_class=fmt,
        description="Camera pose from apriltag detections (or compressed images) "
        "and the tag map, published as PoseStamped.",
    )
    p.add_argument("--map", type=Path, required=True, help="tag_map.yaml / tag_map.csv / folder")
    p.add_argument("--detections-key", default=None, help="default: the profile's, else detections")
    p.add_argument(
        "--camera-info-key", default=None, help="default: the profile's, else camera_info"
    )
    p.add_argument(
        "--image-key",
        default=None,
        help="detect tags in images on this key instead of using detections "
        "(default: the profile's, else none)",
    )
    p.add_argument(
        "--image-type",
        choices=["compressed", "raw"],
        default=None,
        help="default: the profile's, else compressed",
    )
    p.add_argument(
        "--pose-key", default=None, help="output key (default: the profile's, else tag_only_pose)"
    )
    p.add_argument("--frame-id", default="map", help="frame of the poses (default: map)")
    _pipeline(p, "extract's detector and filters, pnp's tag sizes and trajectory's method")
    _profile(p, "the keys and stage parameters (without a pipeline file)")
    g = p.add_argument_group("overrides")
    g.add_argument(
        "--tag-size",
        type=POSITIVE,
        default=None,
        metavar="M",
        help="edge (m) of tags whose size neither the map nor pnp.tag_sizes gives "
        "(default: pnp.tag_size)",
    )
    g.add_argument(
        "--method",
        choices=["auto", "avg", "lsq", "pnp"],
        default=None,
        help="per-frame method (default: trajectory.method)",
    )
    g.add_argument(
        "--min-decision-margin",
        type=NON_NEGATIVE,
        default=None,
        metavar="M",
        help="drop detections with a lower decision margin (default: extract.min_decision_margin)",
    )
    g.add_argument(
        "--max-hamming",
        type=COUNT,
        default=None,
        metavar="N",
        help="drop detections with more corrected bits (default: extract.max_hamming)",
    )
    g.add_argument(
        "--refit-corners",
        choices=["true", "edges", "false"],
        default=None,
        help="images: re-fit the corners to the tag's edges with the intensity-profile model "
        "(true, ~3 ms a tag), by the gradient alone (edges, ~0.3 ms a tag: 30 Hz within a "
        "frame's time; bench/FOLLOW.md) or not (false) (default: extract.refit_corners)",
    )
    g = p.add_argument_group("continuity (docs/LIVE.md)")
    g.add_argument(
        "--smooth",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="pose each frame by a fixed-lag smoother over the last --window seconds with the "
        "offline joint model's priors (motion, ground plane), publishing "
        "<prefix>/pose_with_covariance, <prefix>/fix_age_s and <prefix>/state too "
        "(default: off, each frame on its own)",
    )
    g.add_argument(
        "--window",
        type=POSITIVE,
        default=2.0,
        metavar="S",
        help="the smoother's window (s; at most 60 frames; default 2)",
    )
    g.add_argument(
        "--odom-key",
        default=None,
        metavar="KEY",
        help="with --smooth: nav_msgs/Odometry of the base (e.g. odom): a prior of the "
        "smoother's window and, between frames and without tags, the last fix dead-reckoned "
        "at its rate (default: the profile's, limo: odom; else none)",
    )
    g.add_argument(
        "--odom-latency",
        type=NON_NEGATIVE,
        default=0.005,
        metavar="S",
        help="odometry stamps are publication times: the state is this much older (default 0.005)",
    )
    g.add_argument(
        "--camera-forward",
        dest="camera_forward_m",
        type=FINITE,
        default=None,
        metavar="M",
        help="the camera ahead of the base's turning centre (m; negative: behind it): the "
        "smoother's drive prior "
        "holds it and the dead reckoning turns about it (default: the profile's, limo: 0.084; "
        "else fitted once the drive has turned)",
    )
    g.add_argument(
        "--ground",
        default=None,
        metavar="FILE|none",
        help="with --smooth: the mapping run's ground plane and camera mount (its ground.json, "
        "optimize's export beside tag_map.yaml), held from the first frame while this run's "
        "poses agree with them (default: the ground.json beside --map, if there is one; none: "
        "fitted to this run's own poses once it has travelled 1 m)",
    )
    g.add_argument(
        "--prefix", default="localize", help="prefix of the --smooth outputs (default: %(default)s)"
    )
    _common(p, "stop after N input messages", express=True)
    _foxglove(p)
    _record_arguments(sub, fmt)
    _echo_arguments(sub, fmt)
    _follow_arguments(sub, fmt)
    return parser


def _follow_arguments(sub: Any, fmt: type[argparse.HelpFormatter]) -> None:
    p = sub.add_parser(
        "follow",
        help="drive along the reference: Twist on cmd_vel",
        epilog=EXAMPLES,
        formatter_class=fmt,
        description="A reference path follower (Stanley "
        "or pure pursuit; docs/FOLLOW.md) on relocalize's state JSON, publishing "
        "geometry_msgs/msg/Twist within the robot's limits; a zero Twist when "
        "the pose is stale, lost, bad or at the path's end.",
    )
    p.add_argument(
        "--state-key",
        default="relocalization/state",
        help="relocalize's state JSON (default: %(default)s)",
    )
    p.add_argument("--cmd-key", default=None, help="output key (default: cmd_vel)")
    p.add_argument(
        "--profile",
        choices=["limo"],
        default=None,
        help="the robot's limits and key (limo: 1 m/s, R_min 0.4 m, wheelbase 0.2 m)",
    )
    p.add_argument(
        "--law",
        choices=["stanley", "pure_pursuit"],
        default=None,
        help="control law (default: stanley)",
    )
    p.add_argument(
        "--speed",
        type=POSITIVE,
        default=0.3,
        metavar="M/S",
        help="cruise speed (default 0.3; capped by the profile's)",
    )
    g = p.add_argument_group("path's end (one of)")
    g.add_argument(
        "--reference",
        type=Path,
        default=None,
        help="the reference relocalize follows: its length is where to stop",
    )
    g.add_argument(
        "--plane",
        choices=list(PLANES),
        default=None,
        help="--reference's plane (default: the profile's report.plane, else auto)",
    )
    g.add_argument(
        "--path-length",
        type=POSITIVE,
        default=None,
        metavar="M",
        help="stop when progress_m reaches M (minus --end-tolerance)",
    )
    g.add_argument(
        "--end-tolerance",
        type=NON_NEGATIVE,
        default=0.05,
        metavar="M",
        help="stop this short of the end (default 0.05)",
    )
    g = p.add_argument_group("limits and gains (default: the profile's)")
    for flag, name, what in (
        ("--max-speed", "max_speed_mps", "m/s"),
        ("--min-turn-radius", "min_turn_radius_m", "m"),
        ("--max-accel", "max_accel_mps2", "m/s^2"),
        ("--max-ang-accel", "max_ang_accel_rps2", "rad/s^2"),
        ("--max-lat-accel", "max_lat_accel_mps2", "m/s^2: v <= sqrt(a/|kappa|)"),
        ("--max-yaw-rate", "max_yaw_rate_rps", "rad/s"),
        ("--k", "k", "Stanley's cross-track gain, 1/s"),
        ("--k-soft", "k_soft", "m/s"),
        ("--wheelbase", "wheelbase_m", "m"),
        ("--lookahead", "lookahead_m", "pure pursuit, m"),
        ("--camera-forward", "camera_forward_m", "m: the pose's point ahead of the turning centre"),
    ):
        g.add_argument(flag, dest=name, type=NON_NEGATIVE, default=None, metavar="X", help=what)
    g = p.add_argument_group("safety")
    g.add_argument(
        "--timeout",
        type=POSITIVE,
        default=0.5,
        metavar="S",
        help="stop when the last good pose is older than S (default 0.5)",
    )
    g.add_argument(
        "--max-jump",
        type=NON_NEGATIVE,
        default=0.1,
        metavar="M",
        help="drop a pose whose cross-track jumps more than M (+ v_max*dt) from the "
        "last good one (a bad pose; 0: never; default 0.1)",
    )
    g.add_argument(
        "--no-stamp-check",
        action="store_true",
        help="judge a pose's age by its arrival only (clocks not synchronised)",
    )
    g.add_argument(
        "--plane-normal",
        choices=["down", "up"],
        default="down",
        help="where the plane's n points (default: down, as tagtrail's xz/auto "
        "planes: left about n is the robot's right)",
    )
    _common(p, "stop after N input messages", express=True)


def _echo_arguments(sub: Any, fmt: type[argparse.HelpFormatter]) -> None:
    p = sub.add_parser(
        "echo",
        help="print the messages of a key (e.g. relocalization/state)",
        epilog=ECHO_EXAMPLES,
        formatter_class=fmt,
        description="Print each sample of a key: JSON (the state key) as it is, CDR as its size.",
    )
    p.add_argument("key", help="zenoh key, e.g. relocalization/state")
    p.add_argument("--count", type=COUNT, default=None, metavar="N", help="stop after N")
    p.add_argument(
        "--wait",
        type=POSITIVE,
        default=30.0,
        metavar="S",
        help="error if nothing arrives within S seconds (default 30)",
    )
    add_session_arguments(p)


def _record_arguments(sub: Any, fmt: type[argparse.HelpFormatter]) -> None:
    p = sub.add_parser(
        "record",
        help="record zenoh-bridge-ros2dds topics into a rosbag2",
        epilog=EXAMPLES,
        formatter_class=fmt,
        description="Subscribe to ROS topics forwarded over zenoh (key = topic "
        "without '/', CDR) and write them unchanged into a rosbag2 that ROS 2 and "
        "tagtrail read; log time = receive time. Kept readable while it grows: "
        "after kill -9 run --recover OUT.",
    )
    p.add_argument("out", type=Path, metavar="OUT", help="the bag folder to create")
    p.add_argument(
        "--topic",
        action="append",
        default=[],
        metavar="NAME[:TYPE]",
        help="a topic to record, e.g. /camera_info:sensor_msgs/msg/CameraInfo "
        "(repeatable; type optional when the profile or the bridge gives it)",
    )
    _profile(p, "the topics to record")
    p.add_argument(
        "--storage",
        choices=["mcap", "sqlite3"],
        default="mcap",
        help="bag storage (default: %(default)s)",
    )
    p.add_argument(
        "--max-size",
        default=None,
        metavar="SIZE",
        help="stop when the messages written reach SIZE (500M, 2G)",
    )
    p.add_argument(
        "--wait",
        type=NON_NEGATIVE,
        default=10.0,
        metavar="S",
        help="stop with an error if a topic has no message after S seconds "
        "(0: wait for ever; default 10)",
    )
    p.add_argument(
        "--flush-period",
        type=POSITIVE,
        default=1.0,
        metavar="S",
        help="make the bag readable on disk every S seconds (default 1): at most "
        "that much is lost to a kill -9 or a power cut",
    )
    p.add_argument(
        "--recover",
        action="store_true",
        help="do not record: finish the bag OUT left by a killed recorder",
    )
    g = _run_group(p)
    g.add_argument(
        "--stats-period",
        type=NON_NEGATIVE,
        default=2.0,
        metavar="S",
        help="print the live line (rates, drops) every S seconds (0: never; default 2)",
    )


def build_parser() -> argparse.ArgumentParser:
    return add_arguments(
        argparse.ArgumentParser(
            prog="tagtrail stream", description="Live nodes over eclipse-zenoh."
        )
    )


def main(args: argparse.Namespace | Sequence[str] | None = None) -> int:
    """Run a stream command from parsed arguments (or an argv list); 0 on success."""
    from tagtrail.cli import run_command

    ns = args if isinstance(args, argparse.Namespace) else build_parser().parse_args(args)
    cmd = getattr(ns, "stream_command", None)
    if cmd is None:
        build_parser().print_help()
        return 2
    run = {
        "relocalize": _relocalize,
        "replay": _replay,
        "localize": _localize,
        "record": _record,
        "echo": _echo,
        "follow": _follow,
    }[cmd]
    return run_command(lambda: run(with_profile(ns)))


_BUILTIN_KEYS = {
    "pose_key": "tag_only_pose",
    "detections_key": "detections",
    "camera_info_key": "camera_info",
    "image_key": None,
    "image_type": "compressed",
    "odom_key": None,
    "camera_forward_m": None,
}


def with_profile(ns: argparse.Namespace) -> argparse.Namespace:
    """``ns`` with the keys left unset taken from ``--profile`` (else the built-in defaults),
    and replay's ``--topics`` from the profile when a bag is replayed without them."""
    from tagtrail.schemas.profiles import get_profile

    profile = get_profile(getattr(ns, "profile", None))
    out = argparse.Namespace(**vars(ns))
    for name, default in _BUILTIN_KEYS.items():
        if hasattr(out, name) and getattr(out, name) is None:
            live = getattr(profile.live, name) if profile is not None else None
            setattr(out, name, live if live is not None else default)
    if profile is not None and getattr(out, "stream_command", None) == "replay" and not out.topics:
        src = Path(out.source)
        if src.suffix in (".mcap", ".db3", ".bag") or (src / "metadata.yaml").is_file():
            out.topics = [t for t, _ in profile.record]
            out.optional_topics = list(profile.optional)
    return out


def _wire(ns: argparse.Namespace, session: Any, node: str) -> Any:
    """The command's wire (``--wire``), its node ``tagtrail_<node>`` announced."""
    from tagtrail.stream.wire import wire_from_args

    return wire_from_args(ns, session, f"tagtrail_{node}")


def _relocalize(ns: argparse.Namespace) -> int:
    from tagtrail.io.layouts import read_trajectory
    from tagtrail.stages import report as report_stage
    from tagtrail.stream.foxglove import foxglove_server
    from tagtrail.stream.params import stage_params
    from tagtrail.stream.reloc_node import OUTPUT_TYPES, Relocalizer, load_alignment, serve
    from tagtrail.stream.session import close_all, leave_now, stop_on_signals

    ref = read_trajectory(ns.reference)
    # the alignment file's plane wins over the pipeline's: its planar transform acts in that plane
    report = stage_params(["report"], ns.pipeline, ns.dataset, profile=ns.profile)["report"]
    assert isinstance(report, report_stage.Params)
    if ns.association:
        report = report.model_copy(update={"association": ns.association})
    plane = ns.plane or report.plane
    alignment = None
    if ns.alignment is not None:
        A, R, file_plane = load_alignment(ns.alignment, ref, plane)
        alignment, plane = (A, R), ns.plane or file_plane or plane
    reloc = Relocalizer(
        ref,
        plane,
        alignment,
        ns.frame_id,
        ns.prefix,
        ns.pose_type,
        ns.path_max_points,
        report_stage.track_params(report),
    )
    fox = foxglove_server(ns, "relocalize", {reloc.key[k]: t for k, t in OUTPUT_TYPES.items()})
    session = None
    try:
        session = open_session(config_from_args(ns, "listen"))
        wire = _wire(ns, session, "relocalize")
    except BaseException:
        if fox is not None:
            fox.close()
        close_all(session, [])
        raise
    with stop_on_signals() as stop:
        summary = serve(
            reloc,
            session,
            ns.pose_key,
            congestion=ns.congestion,
            express=ns.express,
            path_period_s=ns.path_period,
            duration_s=ns.duration,
            count=ns.count,
            stats_period_s=ns.stats_period,
            stop=stop,
            foxglove=fox,
            wire=wire,
        )
    if not summary["shutdown_clean"]:
        leave_now(0)  # a zenoh callback thread blocked in a put would hold the exit for 5 s
    return 0


def _replay(ns: argparse.Namespace) -> int:
    from tagtrail.stream.replay import Replayed, bag_messages, load_poses, pose_messages, replay
    from tagtrail.stream.session import close_all, leave_now, stop_on_signals

    if ns.topics:
        messages = bag_messages(ns.source, ns.topics, getattr(ns, "optional_topics", ()))
    else:
        messages = pose_messages(load_poses(ns.source, ns.topic, ns.frame_id), ns.key)
    session = open_session(config_from_args(ns, "connect"))
    done = Replayed(0)
    wire = None
    try:
        wire = _wire(ns, session, "replay")
        with stop_on_signals() as stop:
            done = replay(
                session,
                messages,
                rate=ns.rate,
                count=ns.count,
                wait_s=ns.wait,
                publish_anyway=ns.publish_anyway,
                congestion=ns.congestion,
                express=ns.express,
                stop=stop,
                wire=wire,
                optional=[t.lstrip("/") for t in getattr(ns, "optional_topics", ())],
            )
    finally:
        if wire is not None:
            wire.close()
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

    got = stage_params(
        ["extract", "pnp", "trajectory"],
        ns.pipeline,
        ns.dataset,
        profile=getattr(ns, "profile", None),
    )
    ex, pn, tr = got["extract"], got["pnp"], got["trajectory"]
    assert isinstance(ex, extract.Params) and isinstance(pn, pnp.Params)
    assert isinstance(tr, trajectory.Params)
    return Params(
        extract=override(
            ex,
            {
                "min_decision_margin": ("--min-decision-margin", ns.min_decision_margin),
                "max_hamming": ("--max-hamming", ns.max_hamming),
                "refit_corners": ("--refit-corners", _refit(ns.refit_corners)),
            },
        ),
        pnp=override(pn, {"tag_size": ("--tag-size", ns.tag_size)}),
        trajectory=override(tr, {"method": ("--method", ns.method)}),
    )


def _refit(word: str | None) -> bool | str | None:
    """``--refit-corners``'s word as ``extract.refit_corners``'s value."""
    return {"true": True, "false": False}.get(word, word) if word is not None else None


def _held_ground(ns: argparse.Namespace) -> Any:
    """``--ground``'s :class:`~tagtrail.stream.continuity.HeldGround` (None: none), said in
    the log either way."""
    from tagtrail.io.layouts import ground_beside, read_ground
    from tagtrail.stream.continuity import HeldGround

    log = logging.getLogger("tagtrail.stream")
    path = ns.ground
    if path is None:
        beside = ground_beside(ns.map)
        if not beside.is_file():
            log.info(
                "localize: no ground.json beside the map: the ground plane and the camera's "
                "mount are fitted to this run's poses once it has travelled 1 m (--ground FILE: "
                "a mapping run's, held from the first frame)"
            )
            return None
        path = beside
    elif path == "none":
        log.info("localize: --ground none: the ground plane is fitted to this run's poses")
        return None
    held = HeldGround.of(read_ground(Path(path)))
    log.info(
        "localize: the ground plane of %s held from the first frame (dropped, with a warning, "
        "if this run's camera sits off it)%s",
        path,
        ""
        if held.mount is None
        else "; its camera mount too, unless its lever arm is over 2 cm from --camera-forward's",
    )
    return held


def _localize(ns: argparse.Namespace) -> int:
    from tagtrail.io import msgs
    from tagtrail.io.layouts import read_tag_map
    from tagtrail.stream.foxglove import foxglove_server, teed
    from tagtrail.stream.localize import Localizer, cv2_threads
    from tagtrail.stream.node import Node
    from tagtrail.stream.session import close_all, leave_now, stop_on_signals
    from tagtrail.stream.stats import Stats

    ns = with_profile(ns)
    if ns.low_latency and ns.image_key:
        raise SpecError(
            "--low-latency with --image-key: zenoh's low-latency transport does not fragment, "
            "an image (over 64 KiB) is not for it; leave --low-latency out"
        )
    tags, _ = read_tag_map(ns.map)
    stats = Stats("localize")
    loc = Localizer(tags, localize_params(ns), ns.pose_key, ns.frame_id, stats)
    cv2_threads()
    # the Foxglove server (if asked for) first, as relocalize: a busy port fails before zenoh
    channels = {ns.pose_key: msgs.POSE_STAMPED}
    if ns.smooth:
        channels[f"{ns.prefix}/pose_with_covariance"] = (
            "geometry_msgs/msg/PoseWithCovarianceStamped"
        )
        channels[f"{ns.prefix}/fix_age_s"] = "std_msgs/msg/Float64"
    fox = foxglove_server(ns, "localize", channels)
    session = open_session(config_from_args(ns, "connect"))
    try:
        wire = _wire(ns, session, "localize")
    except BaseException:
        close_all(session, [])
        raise
    node = Node(session, stats, ns.congestion, ns.express, wire)
    node.types.update(
        {
            ns.pose_key: msgs.POSE_STAMPED,
            ns.camera_info_key: msgs.CAMERA_INFO,
            ns.detections_key: msgs.DETECTIONS,
        }
    )
    if ns.image_key:
        node.types[ns.image_key] = (
            msgs.COMPRESSED_IMAGE if ns.image_type == "compressed" else msgs.IMAGE
        )
    node.count = ns.count
    live, background = None, None
    if ns.ground is not None and not ns.smooth:
        logging.getLogger("tagtrail.stream").warning(
            "localize: --ground is for --smooth (the smoother's ground plane): ignored"
        )
    if ns.smooth:
        from tagtrail.stream.background import Background
        from tagtrail.stream.continuity import (
            RESOLVE,
            DeadReckoning,
            LivePoses,
            Smoother,
            SmootherSettings,
        )

        if ns.camera_forward_m is None:
            logging.getLogger("tagtrail.stream").warning(
                "localize: --smooth without --camera-forward (nor a profile giving it): the "
                "camera's lever arm is taken as 0 until the robot has turned 0.5 rad and it can "
                "be fitted; give it (m ahead of the base's turning centre; LIMO 0.084) for "
                "better poses from the start"
            )

        live = LivePoses(
            Smoother(
                loc.world_T_tag,
                loc.size_m,
                SmootherSettings(
                    window_s=ns.window, lever_m=ns.camera_forward_m, ground=_held_ground(ns)
                ),
            ),
            DeadReckoning(latency_s=ns.odom_latency, camera_forward_m=ns.camera_forward_m or 0.0),
            ns.pose_key,
            ns.prefix,
            ns.frame_id,
        )
        loc.smooth(live)
        node.types.update(live.keys())
        # the window re-solved once the pose is out, in a process of the lowest priority
        background = live.smoother.background = Background(RESOLVE, "localize: window re-solve")
        background.start()  # its imports done while the node starts, not on the first frames
        node.after.append(live.dispatch)
    try:
        node.publisher(ns.pose_key)
        if live is not None and ns.odom_key:
            node.types[ns.odom_key] = "nav_msgs/msg/Odometry"
            node.subscribe(ns.odom_key, teed(fox, live.on_odometry))
        # its outputs: the inputs kept until the first CameraInfo
        node.subscribe(ns.camera_info_key, teed(fox, loc.on_camera_info))
        if ns.image_key:
            node.subscribe(
                ns.image_key, teed(fox, lambda b: loc.on_image(b, ns.image_type)), latest_only=True
            )
        else:
            node.subscribe(ns.detections_key, teed(fox, loc.on_detections))
    except BaseException:
        node.close()
        raise
    try:
        with stop_on_signals() as stop:
            node.run(ns.duration, ns.stats_period, stop)
    finally:
        if background is not None:
            background.close()
    if fox is not None:
        fox.close()  # on an error before this, the SDK stops it at exit (atexit)
    if ns.image_key or not node.clean:
        # pupil-apriltags may segfault in its destructor at interpreter exit (NOTES; upstream
        # pupil-labs/apriltags#46), and a zenoh callback blocked in a put would hold the exit
        # for 5 s: the session is closed (or abandoned) and stats printed, so leave at once
        leave_now(0)
    return 0


def _follow(ns: argparse.Namespace) -> int:
    from tagtrail.stream.follow import Follower, FollowerNode, Gains, Limits, serve, with_profile
    from tagtrail.stream.session import stop_on_signals
    from tagtrail.stream.stats import Stats

    names = (
        "max_speed_mps",
        "min_turn_radius_m",
        "max_accel_mps2",
        "max_ang_accel_rps2",
        "max_lat_accel_mps2",
        "max_yaw_rate_rps",
        "k",
        "k_soft",
        "wheelbase_m",
        "lookahead_m",
        "camera_forward_m",
        "law",
    )
    over = {n: getattr(ns, n) for n in names} | {"cmd_key": ns.cmd_key}
    limits, gains, cmd_key = with_profile(Limits(), Gains(), ns.profile, over)
    length, closed = ns.path_length, False
    if ns.reference is not None and length is None:
        length, closed = _path_length(ns)
    fol = Follower(
        limits,
        gains,
        ns.speed,
        length,
        ns.end_tolerance,
        ns.timeout,
        not ns.no_stamp_check,
        ns.plane_normal == "down",
        ns.max_jump,
        closed=closed,
    )
    session = open_session(config_from_args(ns, "connect"))
    try:
        wire = _wire(ns, session, "follow")
        node = FollowerNode(session, Stats("follow"), ns.congestion, ns.express, wire)
    except BaseException:
        from tagtrail.stream.session import close_all

        close_all(session, [])
        raise
    node.count = ns.count
    with stop_on_signals() as stop:
        serve(fol, node, ns.state_key, cmd_key, ns.duration, ns.stats_period, stop)
    return 0


def _path_length(ns: argparse.Namespace) -> tuple[float, bool]:
    """Planar arc length of ``--reference`` in its plane (relocalize's ``progress_m`` scale) and
    whether relocalize's tracker takes it for a loop (its progress wraps)."""
    from tagtrail.geometry.association import PathTracker
    from tagtrail.geometry.reference_path import ReferencePath, reference_plane
    from tagtrail.io.layouts import read_trajectory
    from tagtrail.schemas.artifacts import poses
    from tagtrail.stages import report as report_stage
    from tagtrail.stream.params import stage_params

    plane = ns.plane
    if plane is None:
        report = stage_params(["report"], None, None, profile=ns.profile)["report"]
        assert isinstance(report, report_stage.Params)
        plane = report.plane
    P, R = poses(read_trajectory(ns.reference))
    tracker = PathTracker(ReferencePath(P, reference_plane(plane, P, R)))
    return float(tracker.s[-1]), tracker.closed


def _record(ns: argparse.Namespace) -> int:
    from tagtrail.schemas.profiles import get_profile
    from tagtrail.stream.bagwriter import CrashSafeWriter, recover
    from tagtrail.stream.record import Recorder, parse_size, resolve_topics, summary_line
    from tagtrail.stream.session import close_all, stop_on_signals

    if ns.recover:
        say(recover(ns.out))
        return 0
    profile = get_profile(ns.profile)
    max_size = parse_size(ns.max_size) if ns.max_size else None
    if ns.out.exists():
        raise SourceError(
            f"{ns.out} exists already; record into a new folder (or --recover "
            f"{ns.out} to finish a recording that was killed)"
        )
    session = open_session(config_from_args(ns, "connect"))
    wire = None
    try:
        wire = _wire(ns, session, "record")
        # the bridge's admin space (or rmw_zenoh's liveliness tokens): topics when none are
        # named, types for names without one, and a check of the types given
        topics = resolve_topics(ns.topic, profile, wire.discover())
        writer = CrashSafeWriter(ns.out, ns.storage, flush_s=ns.flush_period)
        rec = Recorder(session, topics, writer, wait_s=ns.wait, max_size=max_size, wire=wire)
        with stop_on_signals() as stop:
            done = rec.run(ns.duration, ns.stats_period, stop)
        say(summary_line(done, writer))
        if wire.summary():
            say(f"record: {json.dumps(wire.summary())}")
    finally:
        if wire is not None:
            wire.close()
        close_all(session, [])
    return 0


def _echo(ns: argparse.Namespace) -> int:
    import queue
    import time

    from tagtrail.stream.session import close_all, stop_on_signals

    got: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    session = open_session(config_from_args(ns, "connect"))
    try:
        wire = _wire(ns, session, "echo")
        sub = wire.declare_subscriber(ns.key, None, lambda s: got.put(s.payload.to_bytes()))
    except BaseException:
        close_all(session, [])
        raise
    n, deadline = 0, time.monotonic() + ns.wait
    try:
        with stop_on_signals() as stop:
            while not stop.is_set() and (ns.count is None or n < ns.count):
                try:
                    data = got.get(timeout=0.1)
                except queue.Empty:
                    if n == 0 and time.monotonic() > deadline:
                        raise SourceError(f"no message on {ns.key} after {ns.wait:g} s") from None
                    continue
                n += 1
                text = (
                    data.decode("utf-8", "replace")
                    if data[:1] in (b"{", b"[")
                    else (f"<{len(data)} bytes of CDR>")
                )
                say(f"{ns.key}: {text}")
    finally:
        wire.close()
        close_all(session, [sub])
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    sys.exit(main())

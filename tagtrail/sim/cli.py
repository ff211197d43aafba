"""``tagtrail simulate``: argparse wiring around :func:`tagtrail.sim.simulate`."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

from tagtrail.errors import SpecError
from tagtrail.sim.camera import limo_camera
from tagtrail.sim.render import Realism
from tagtrail.sim.scenarios import SCENARIOS, SimOptions
from tagtrail.sim.simulate import simulate

EXAMPLES = """\
scenarios (recordings written under OUT):
  circle        24 tags around a circular path (paper's simulation)     -> circle
  room          loop in a room + 3 parked test poses (the demo)          -> reference, query_1..3
  corridor      long path, one or two tags in view at a time             -> corridor
  hall          sparse: tags flat on both walls, 1-3 in view, U-turn    -> hall
  corridor_gap  the corridor with a blank wall: ~5 s without a tag      -> corridor_gap
  room_blank_turn  the room's loop, a turn at a bare wall: ~2 s without a tag -> room_blank_turn
  observations  cam_T_tag observations from rigid transforms (+ noise)  -> observations
  follow        closed loop: simulated LIMO + stream localize/relocalize/follow over zenoh
                on 127.0.0.1 -> follow.csv, follow_summary.json, follow.png, ground_truth/

examples:
  tagtrail simulate room --out demo/data
  tagtrail simulate room --out sim --detections --storage sqlite3
  tagtrail simulate circle --out sim --frames 300 --compressed --seed 7
  tagtrail simulate observations --out sim --noise-t 0.10 --noise-r-deg 2
  tagtrail simulate corridor --out sim --odom-scale-error 0.02 --odom-slip 5,1,0.2
  tagtrail simulate follow --out runs/eight --start-offset 0.3 --start-heading 30
  tagtrail simulate follow --out runs/blackout --blackout 2
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``tagtrail simulate``'s arguments to ``parser``."""
    parser.description = (
        "Render simulated rosbag2 recordings (or observations) among tag36h11 "
        "tags, with ground truth in OUT/<recording>/ground_truth/."
    )
    parser.epilog = EXAMPLES
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    a = parser.add_argument
    o = SimOptions  # one default per option: SimOptions'
    a(
        "scenario",
        metavar="SCENARIO",
        choices=(*SCENARIOS, "follow"),
        help=" | ".join((*SCENARIOS, "follow")),
    )
    a("--out", "-o", type=Path, required=True, metavar="DIR", help="output folder")
    a("--storage", choices=("mcap", "sqlite3"), default=o.storage, help="bag storage (%(default)s)")
    a("--compressed", action="store_true", help="jpeg CompressedImage instead of raw rgb8")
    a(
        "--jpeg-quality",
        type=int,
        default=o.jpeg_quality,
        metavar="Q",
        help="jpeg quality (%(default)s)",
    )
    a(
        "--detections",
        action="store_true",
        help="write /detections (apriltag_msgs) + /camera_info instead of images",
    )
    a(
        "--seed",
        type=int,
        default=o.seed,
        help="random seed: same seed, same recordings (%(default)s)",
    )
    a("--force", action="store_true", help="overwrite existing recordings")
    a("--no-progress", action="store_true", help="no progress bar")
    g = parser.add_argument_group("path and timing")
    g.add_argument(
        "--frames",
        type=int,
        metavar="N",
        help="frames of a moving recording (default: path length / speed * fps)",
    )
    g.add_argument("--fps", type=float, default=o.fps, help="frame rate (%(default)s)")
    g.add_argument(
        "--speed", type=float, default=o.speed_mps, metavar="M_S", help="speed, m/s (%(default)s)"
    )
    g.add_argument(
        "--query-frames",
        type=int,
        default=o.query_frames,
        metavar="N",
        help="frames of each parked query recording (%(default)s)",
    )
    g = parser.add_argument_group("tags and camera")
    g.add_argument(
        "--tag-size",
        type=float,
        default=o.tag_size_m,
        metavar="M",
        help="edge of the black square, m (%(default)s: the pipeline's pnp.tag_size)",
    )
    g.add_argument("--tag-sizes", metavar="ID=M,...", help="per-id sizes, e.g. 0=0.2,5=0.1")
    g.add_argument(
        "--tag-ids", metavar="IDS", help="relabel the tags in layout order: 10-33 or 1,4,7"
    )
    g.add_argument("--anchor", type=int, metavar="ID", help="anchor tag (default: first tag)")
    g.add_argument("--size", metavar="WxH", help="image size; the LIMO lens scaled (640x480)")
    g = parser.add_argument_group("noise and realism")
    g.add_argument(
        "--noise-t",
        type=float,
        default=o.noise_t_m,
        metavar="M",
        help="observations: translation noise std per axis, m (paper: 0.10)",
    )
    g.add_argument(
        "--noise-r-deg",
        type=float,
        default=o.noise_r_deg,
        metavar="DEG",
        help="observations: rotation noise std per axis, degrees",
    )
    g.add_argument(
        "--corner-noise",
        type=float,
        default=o.corner_noise_px,
        metavar="PX",
        help="--detections: corner noise std, px (%(default)s)",
    )
    g.add_argument(
        "--max-range",
        type=float,
        default=o.max_range_m,
        metavar="M",
        help="detections/observations: farthest tag reported, m (%(default)s)",
    )
    g = parser.add_argument_group("wheel odometry (/odom, /tf_static; tagtrail.sim.odometry)")
    g.add_argument(
        "--odom",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="write /odom (50 Hz) and /tf_static base_link -> camera (default: yes for bags)",
    )
    g.add_argument(
        "--odom-scale-error",
        type=float,
        default=None,
        metavar="REL",
        help="both wheels' scale error, e.g. 0.02 (default: drawn 1-3 %% per wheel, either sign)",
    )
    g.add_argument(
        "--odom-slip",
        metavar="START,DUR,FRAC",
        help="a stretch of wheel slip: from START s for DUR s, the wheels over-read by FRAC "
        "(5,1,0.2: 1 s of 20 %% slip)",
    )
    r = Realism()
    f = parser.add_argument_group("follow (closed loop; docs/FOLLOW.md)")
    f.add_argument(
        "--reference",
        type=Path,
        default=None,
        help="trajectory to follow, in the scene's world (default: the figure eight's "
        "ground truth)",
    )
    f.add_argument(
        "--start-offset",
        type=float,
        default=0.3,
        metavar="M",
        help="start this far left of the reference's start (%(default)s)",
    )
    f.add_argument(
        "--start-heading",
        type=float,
        default=30.0,
        metavar="DEG",
        help="start turned this far left of the reference (%(default)s)",
    )
    f.add_argument(
        "--blackout",
        type=float,
        default=0.0,
        metavar="S",
        help="no tag in view for S seconds from mid-path (%(default)s)",
    )
    f.add_argument(
        "--law",
        choices=("stanley", "pure_pursuit"),
        default="stanley",
        help="stream follow's control law (%(default)s)",
    )
    f.add_argument(
        "--smooth",
        action="store_true",
        help="stream localize --smooth with the LIMO's /odom (dead reckoning between frames "
        "and through a blackout) instead of each frame on its own",
    )
    f.add_argument(
        "--low-latency",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the nodes' links on zenoh's low-latency transport (stream ... --low-latency; "
        "never the images'; default: on)",
    )
    f.add_argument(
        "--images",
        action="store_true",
        help="render 640x480 images (stream localize detects the tags) instead of "
        "publishing detections",
    )
    g.add_argument(
        "--image-noise",
        type=float,
        default=r.noise_sigma,
        metavar="DN",
        help=f"sensor noise std, grey levels ({r.noise_sigma})",
    )
    g.add_argument(
        "--blur",
        type=float,
        default=r.blur_sigma,
        metavar="PX",
        help=f"Gaussian blur sigma, px ({r.blur_sigma})",
    )
    g.add_argument("--exposure", type=float, default=r.exposure, help="exposure gain (1.0)")
    g.add_argument("--contrast", type=float, default=r.contrast, help="contrast (1.0)")
    g.add_argument(
        "--exposure-jitter",
        type=float,
        default=r.exposure_jitter,
        metavar="REL",
        help=f"slow exposure drift, relative std ({r.exposure_jitter})",
    )


def _int_list(text: str) -> tuple[int, ...]:
    out: list[int] = []
    for part in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if m is None:
            raise SpecError(f"--tag-ids: cannot parse {part!r} (use e.g. 10-33 or 1,4,7)")
        lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
        out.extend(range(lo, hi + 1))
    return tuple(out)


def _slip(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        start, dur, frac = (float(p) for p in parts)
    except ValueError as err:
        raise SpecError(f"--odom-slip: cannot parse {text[:80]!r} (use e.g. 5,1,0.2)") from err
    return start, dur, frac


def _sizes(text: str) -> dict[int, float]:
    try:
        pairs = [p.split("=") for p in text.split(",") if p.strip()]
        sizes = {int(k): float(v) for k, v in pairs}
    except ValueError as err:
        raise SpecError(f"--tag-sizes: cannot parse {text[:80]!r} (use e.g. 0=0.2,5=0.1)") from err
    lo, hi = next((lo, hi) for flag, lo, hi in RANGES if flag == "--tag-size")
    bad = {k: v for k, v in sizes.items() if not lo <= v <= hi}
    if bad:
        k, v = next(iter(bad.items()))
        raise SpecError(f"--tag-sizes: {k}={v:g} is out of range ({lo:g} to {hi:g} m)")
    return sizes


MAX_SIDE_PX = 8192  # the live node's limit on an image's side, too
RANGES: tuple[tuple[str, float, float], ...] = (  # a value outside: one error line
    ("--frames", 1, 1_000_000),
    ("--query-frames", 1, 1_000_000),
    ("--fps", 0.01, 1000.0),
    ("--speed", 1e-3, 100.0),
    ("--tag-size", 1e-3, 10.0),
    ("--jpeg-quality", 0, 100),
    ("--noise-t", 0.0, 10.0),
    ("--noise-r-deg", 0.0, 180.0),
    ("--corner-noise", 0.0, 100.0),
    ("--max-range", 0.01, 1000.0),
    ("--image-noise", 0.0, 255.0),
    ("--blur", 0.0, 100.0),
    ("--exposure", 0.0, 100.0),
    ("--contrast", 0.0, 100.0),
    ("--exposure-jitter", 0.0, 10.0),
    ("--odom-scale-error", -0.5, 0.5),
)


def options_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword options for :func:`simulate` from parsed arguments."""
    camera = limo_camera()
    if args.size:
        m = re.fullmatch(r"(\d+)[xX](\d+)", args.size)
        if m is None:
            raise SpecError(f"--size: cannot parse {args.size!r} (use e.g. 640x480)")
        width, height = int(m.group(1)), int(m.group(2))
        if width < 16 or height < 16:
            raise SpecError(f"--size: {args.size} is too small (at least 16x16)")
        if width > MAX_SIDE_PX or height > MAX_SIDE_PX:
            raise SpecError(
                f"--size: {args.size[:40]} is too large (at most {MAX_SIDE_PX} px a side)"
            )
        camera = camera.scaled(width, height)
    for flag, lo, hi in RANGES:
        v = getattr(args, flag.removeprefix("--").replace("-", "_"))
        if v is not None and not (lo <= v <= hi):  # NaN fails too
            raise SpecError(f"{flag}: {v:g} is out of range ({lo:g} to {hi:g})")
    return {
        "storage": args.storage,
        "compressed": args.compressed,
        "jpeg_quality": args.jpeg_quality,
        "detections": args.detections,
        "seed": args.seed,
        "force": args.force,
        "progress": not args.no_progress and sys.stderr.isatty(),
        "frames": args.frames,
        "fps": args.fps,
        "speed_mps": args.speed,
        "query_frames": args.query_frames,
        "tag_size_m": args.tag_size,
        "tag_sizes_m": _sizes(args.tag_sizes) if args.tag_sizes else {},
        "tag_ids": _int_list(args.tag_ids) if args.tag_ids else None,
        "anchor_id": args.anchor,
        "camera": camera,
        "noise_t_m": args.noise_t,
        "noise_r_deg": args.noise_r_deg,
        "corner_noise_px": args.corner_noise,
        "max_range_m": args.max_range,
        "realism": Realism(
            args.image_noise, args.blur, args.exposure, args.contrast, args.exposure_jitter
        ),
        "odom": args.odom,
        "odom_scale_error": args.odom_scale_error,
        "odom_slip": _slip(args.odom_slip) if args.odom_slip else None,
    }


def main(args: argparse.Namespace) -> int:
    """Run ``tagtrail simulate``; one line per recording. Exit code 0, or 2 on bad options."""
    from tagtrail.cli import run_command

    return run_command(lambda: _simulate(args))


def _simulate(args: argparse.Namespace) -> int:
    if args.scenario == "follow":
        return _follow(args)
    written = simulate(args.scenario, args.out, **options_from_args(args))
    for name, folder in written.items():
        print(f"{name}: {folder}  (ground truth: {folder / 'ground_truth'})")
    return 0


def _follow(args: argparse.Namespace) -> int:
    import json

    from tagtrail.sim.follow import run

    if args.speed <= 0 or args.speed > 1.0 or args.blackout < 0:
        raise SpecError("follow: --speed must be in (0, 1] m/s and --blackout >= 0")
    if (args.out / "follow_summary.json").exists() and not args.force:
        raise SpecError(f"{args.out} holds a follow run already; use --force to overwrite it")
    s = run(
        args.out,
        reference=args.reference,
        start_offset_m=args.start_offset,
        start_heading_deg=args.start_heading,
        speed_mps=args.speed,
        blackout_s=args.blackout,
        seed=args.seed,
        law=args.law,
        images=args.images,
        smooth=args.smooth,
        low_latency=args.low_latency,
    )
    keys = ("converged_s", "cross_track_rms_m", "cross_track_max_m", "completed")
    print(json.dumps({k: s[k] for k in keys}))
    print(
        f"follow: {args.out / 'follow.csv'}, {args.out / 'follow_summary.json'}, "
        f"{args.out / 'follow.png'}"
    )
    return 0


if __name__ == "__main__":
    _p = argparse.ArgumentParser(prog="tagtrail simulate")
    add_arguments(_p)
    raise SystemExit(main(_p.parse_args()))

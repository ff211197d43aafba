"""Benchmark: stage extract vs a bare single-process detector loop on the same frames.

Packs real photos (../shared/realdata/upenn_ar_tag36h11_id12_seq, 640x480, twice over) into a
rosbag2 (MCAP) in a temp dir — once as CompressedImage (JPEG), once as rgb8 Image — and times:

- bare: one process, frames decoded beforehand (not timed), ``detector.detect`` in a loop with
  the same settings as extract (quad_decimate 2, …);
- extract: ``tagtrail.stages.extract.run`` end to end (open bag, read, ship chunks to worker
  processes, decode there, detect, re-fit corners, build tables), with workers = 1 and = all
  cores, and with all cores without the corner re-fit (``refit_corners: false``, what the bare
  loop does). Worker
  processes are kept for reuse between runs (as in a pipeline), so their start-up (~0.3 s) is
  paid by the first repeat only; ``--cold`` starts them afresh every time.

Prints frames/s (median of ``--repeats``), the ratios extract / bare — the same work: extract
with the re-fit against the loop with ``detect`` + re-fit, extract without it against the bare
detector — and CPU ms per frame (parent + workers), the load-independent cost.
Run: ``.venv/bin/python bench/bench_extract.py [--repeats 3] [--copies 2]``.
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from tagtrail import pool as workers_mod
from tagtrail.geometry.camera import CameraModel
from tagtrail.io import msgs
from tagtrail.io.camera_files import read_camera_file
from tagtrail.io.sources import open_source
from tagtrail.schemas.pipeline import DatasetConfig
from tagtrail.stages import extract
from tagtrail.vision.apriltag import detect, get_detector
from tagtrail.vision.detector import DetectorConfig

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
T0 = 1_700_000_000_000_000_000


def write_bag(path: Path, files: list[Path], cam: CameraModel, compressed: bool) -> None:
    ts = msgs.typestore()
    Time, Header = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    P = np.zeros((3, 4))
    P[:, :3] = cam.K

    def hdr(t: int) -> object:
        return Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id="camera")

    info = ts.types[msgs.CAMERA_INFO](
        header=hdr(T0),
        height=cam.height,
        width=cam.width,
        distortion_model=cam.distortion_model,
        d=np.asarray(cam.D, float),
        k=cam.K.reshape(-1).copy(),
        r=np.eye(3).reshape(-1),
        p=P.reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=ts.types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/camera/camera_info", msgs.CAMERA_INFO, typestore=ts)
        mtype = msgs.COMPRESSED_IMAGE if compressed else msgs.IMAGE
        im = w.add_connection("/camera/image_raw", mtype, typestore=ts)
        w.write(ci, T0, ts.serialize_cdr(info, msgs.CAMERA_INFO))
        for k, f in enumerate(files):
            t = T0 + k * 33_333_333
            if compressed:
                msg = ts.types[mtype](
                    header=hdr(t), format="jpeg", data=np.frombuffer(f.read_bytes(), np.uint8)
                )
            else:
                rgb = np.ascontiguousarray(cv2.imread(str(f))[..., ::-1])
                msg = ts.types[mtype](
                    header=hdr(t),
                    height=rgb.shape[0],
                    width=rgb.shape[1],
                    encoding="rgb8",
                    is_bigendian=0,
                    step=rgb.shape[1] * 3,
                    data=rgb.reshape(-1),
                )
            w.write(im, t, ts.serialize_cdr(msg, mtype))


def cpu_s() -> float:
    """CPU seconds (user + sys) of this process, its reaped children and its live children
    (extract keeps its worker processes for reuse; Linux /proc)."""
    me, kids = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    total = me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime
    tick = os.sysconf("SC_CLK_TCK")
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == os.getpid():  # ppid; utime, stime = fields 11, 12
            total += (int(fields[11]) + int(fields[12])) / tick
    return total


def bare_fps(
    frames: list[Any],
    cfg: DetectorConfig,
    repeats: int,
    decode: Any = None,
    refit: CameraModel | None = None,
) -> tuple[float, float]:
    """(frames/s, CPU ms/frame) of a plain loop over the frames (``decode``d first if given);
    with ``refit`` (the camera), tagtrail's ``detect`` (detector + filters + corner re-fit)."""
    det = get_detector(cfg)
    decode = decode or (lambda img: img)
    run = (lambda img: detect(img, cfg, refit)) if refit is not None else det.detect
    run(decode(frames[0]))  # warm-up
    times, cpus = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), cpu_s()
        for img in frames:
            run(decode(img))
        times.append(time.perf_counter() - t)
        cpus.append(cpu_s() - c)
    return len(frames) / statistics.median(times), 1e3 * statistics.median(cpus) / len(frames)


def extract_fps(
    bag: Path, workers: int, repeats: int, cold: bool, refit: bool = True
) -> tuple[float, float]:
    """(frames/s, CPU ms/frame incl. workers) of stage extract end to end."""
    times, cpus = [], []
    for _ in range(repeats):
        if cold:
            workers_mod._close_idle()
        t, c = time.perf_counter(), cpu_s()
        params = extract.Params(workers=workers, refit_corners=refit)
        with open_source(DatasetConfig(source=bag)) as src:
            out = extract.run(src, params)
        times.append(time.perf_counter() - t)
        cpus.append(cpu_s() - c)
    n = len(out["frames"])
    return n / statistics.median(times), 1e3 * statistics.median(cpus) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--copies", type=int, default=2, help="times the 93 frames are repeated")
    ap.add_argument("--cold", action="store_true", help="new worker processes for every run")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    folder = REALDATA / "upenn_ar_tag36h11_id12_seq" / "frames"
    files = sorted(folder.glob("frame*.jpg")) * args.copies
    cam = read_camera_file(folder / "camera.yaml")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    cfg = extract.Params().detector()
    print(
        f"{len(files)} frames 640x480 (real photos), {cores} cores, "
        f"load average {os.getloadavg()[0]:.1f}, median of {args.repeats}"
        f"{', cold workers' if args.cold else ''}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for compressed in (True, False):
            kind = "CompressedImage jpeg" if compressed else "Image rgb8"
            bag = Path(tmp) / ("jpeg" if compressed else "rgb8")
            write_bag(bag, files, cam, compressed)
            frames = [
                cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
                if compressed
                else cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2GRAY)
                for f in files
            ]
            (bare, bare_cpu) = bare_fps(frames, cfg, args.repeats)
            (bare_fit, bare_fit_cpu) = bare_fps(frames, cfg, args.repeats, refit=cam)
            if compressed:
                encoded = [np.frombuffer(f.read_bytes(), np.uint8) for f in files]
                (dec, dec_cpu) = bare_fps(
                    encoded, cfg, args.repeats, lambda b: cv2.imdecode(b, cv2.IMREAD_GRAYSCALE)
                )
            else:
                encoded = [np.ascontiguousarray(cv2.imread(str(f))[..., ::-1]) for f in files]
                (dec, dec_cpu) = bare_fps(
                    encoded, cfg, args.repeats, lambda b: cv2.cvtColor(b, cv2.COLOR_RGB2GRAY)
                )
            (one, one_cpu) = extract_fps(bag, 1, args.repeats, args.cold)
            (many, many_cpu) = extract_fps(bag, 0, args.repeats, args.cold)
            (plain, plain_cpu) = extract_fps(bag, 0, args.repeats, args.cold, refit=False)
            print(
                f"{kind}:\n"
                f"  bare loop (1 process, pre-decoded) {bare:6.1f} frames/s  "
                f"CPU {bare_cpu:.2f} ms/frame\n"
                f"  bare loop incl. decoding          {dec:6.1f} frames/s  "
                f"CPU {dec_cpu:.2f} ms/frame\n"
                f"  bare loop + corner re-fit          {bare_fit:6.1f} frames/s  "
                f"CPU {bare_fit_cpu:.2f} ms/frame\n"
                f"  extract workers=1 {one:6.1f} frames/s ({one / bare_fit:.2f}x the loop with "
                f"re-fit)  CPU {one_cpu:.2f} ms/frame\n"
                f"  extract workers={cores} {many:6.1f} frames/s ({many / bare_fit:.2f}x the "
                f"loop with re-fit, {many / bare:.2f}x without)  CPU {many_cpu:.2f} ms/frame\n"
                f"  extract workers={cores}, no re-fit {plain:6.1f} frames/s "
                f"({plain / bare:.2f}x)  CPU {plain_cpu:.2f} ms/frame"
            )


if __name__ == "__main__":
    main()

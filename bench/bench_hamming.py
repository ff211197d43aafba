"""Benchmark: the evidence for ``extract.max_hamming``'s default -- recall against false
detections at each number of corrected bits (0-3), on real and rendered images, on images with
no tags at all, and on TagSLAM's real detection bags.

Image sets (gray frames; detection in one worker process through
``tagtrail.vision.apriltag.detect`` with extract's defaults but ``max_hamming``; each at
``min_decision_margin`` 20 -- the default -- and 0, the filter off):

- ``swatbotics``, ``duckietown``, ``photonvision``, ``sim``: as ``bench/bench_recall.py`` defines
  them (present tags and the judge of a false detection);
- ``checkerboards``: the 17 real checkerboard photos of swatbotics' calibration: a checkerboard
  on the room's wall, some of the room's tags (0-19) beside it; any other id is false;
- ``noise``: 30 frames 640x480 of Gaussian noise on a grey ramp (no tag);
- ``fake_tags``: 100 frames of 40 tag-like squares each (a black border around 6x6 random bits
  in a white quiet zone, random size, rotation and perspective, blurred and noised) and 4 true
  tags drawn alike (the control): a decode that is not one of the 4 is a false detection -- the
  worst case for the decoder, 4000 random codes (at 3 bits ~2.7e-4 of them decode by chance).

Detection bags (``../shared/realdata/tagslam_test_1`` and ``_16``, the MIT detector's output):
detections per hamming value, and the agreement of tagtrail's default trajectory with TagSLAM's
(``reference.bag``; SE(3) fit on positions, frames matched by stamp) at ``max_hamming`` 0 and 2.

Run: ``.venv/bin/python bench/bench_hamming.py [--sets swatbotics,fake_tags,tagslam]``.
"""

from __future__ import annotations

import argparse
import bz2
import multiprocessing as mp
import sys
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_recall  # the shared image sets

from tagtrail.stages import extract

REALDATA = bench_recall.REALDATA
HAMMING = (0, 1, 2, 3)
MARGINS = (20.0, 0.0)


def checkerboards() -> bench_recall.Set:
    files = sorted((REALDATA / "swatbotics_mapping_feb_2014" / "calibration").glob("*.JPG"))
    return bench_recall.Set(
        [bench_recall._gray(f) for f in files], None, lambda _k, tag, _c: tag not in range(20)
    )


def noise(n: int = 30, seed: int = 1) -> bench_recall.Set:
    rng = np.random.default_rng(seed)
    ramp = np.linspace(60, 190, 640)[None, :].repeat(480, axis=0)
    frames = [
        np.clip(ramp + rng.normal(0, 12 + 4 * (k % 5), ramp.shape), 0, 255).astype(np.uint8)
        for k in range(n)
    ]
    return bench_recall.Set(frames, [set() for _ in frames], lambda _k, _t, _c: True)


def fake_tags(n: int = 100, per_frame: int = 40, real: int = 4, seed: int = 2) -> bench_recall.Set:
    """Tag-like squares with random 6x6 payloads (module docstring), and ``real`` true tags per
    frame drawn the same way (the control: the quads are found and decoded)."""
    from tagtrail.sim.render import tag_bits

    rng = np.random.default_rng(seed)
    frames, present = [], []
    for _ in range(n):
        img = np.full((720, 1280), 150.0) + rng.normal(0, 20, (720, 1280)).cumsum(1) * 0.02
        ids = {int(i) for i in rng.choice(587, real, replace=False)}
        codes = [tag_bits(i).astype(float) for i in sorted(ids)]
        for _ in range(per_frame):
            cells = np.ones((10, 10))  # quiet zone (white) around the 8x8 tag
            cells[1:9, 1:9] = 0.0  # black border
            cells[2:8, 2:8] = rng.integers(0, 2, (6, 6))
            codes.append(cells)
        for cells in codes:
            side = rng.uniform(40, 110) * 1.25  # with the quiet zone
            patch = cv2.resize(cells, (100, 100), interpolation=cv2.INTER_NEAREST) * 200 + 25
            src = np.float32([[0, 0], [100, 0], [100, 100], [0, 100]])
            c = rng.uniform([side, side], [1280 - side, 720 - side])
            a = rng.uniform(0, 2 * np.pi)
            sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side / 2
            rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            dst = np.float32(sq @ rot.T + c + rng.normal(0, side * 0.04, (4, 2)))
            H = cv2.getPerspectiveTransform(src, dst)
            warped = cv2.warpPerspective(
                patch, H, (1280, 720), flags=cv2.INTER_LINEAR, borderValue=-1
            )
            img = np.where(warped >= 0, warped, img)
        img = cv2.GaussianBlur(img, (0, 0), 0.8) + rng.normal(0, 3, img.shape)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
        present.append(ids)
    return bench_recall.Set(frames, present, lambda k, tag, _c: tag not in present[k])


IMAGE_SETS = {
    **bench_recall.SETS,
    "checkerboards": checkerboards,
    "noise": noise,
    "fake_tags": fake_tags,
}


def _detect_all(frames: list[np.ndarray]) -> dict[tuple[int, float], list[tuple[Any, Any]]]:
    """Per (max_hamming, min_decision_margin): detections per frame -- runs in the worker."""
    from tagtrail.vision.apriltag import detect

    cv2.setNumThreads(1)
    out = {}
    for h in HAMMING:
        for m in MARGINS:
            cfg = extract.Params(max_hamming=h, min_decision_margin=m).detector()
            out[(h, m)] = [detect(f, cfg) for f in frames]
    return out


def images(names: list[str]) -> None:
    ctx = mp.get_context("forkserver")
    pool = ctx.Pool(1)
    try:
        print(
            f"{'set':13} {'margin':>6} "
            + " ".join(f"{'h' + str(h) + ' hit/false':>14}" for h in HAMMING)
            + f" {'present':>7}"
        )
        for name in names:
            data = IMAGE_SETS[name]()
            res = pool.apply(_detect_all, (data.frames,))
            ref = data.present or [set(ints[:, 0].tolist()) for ints, _ in res[(0, 0.0)]]
            present = sum(len(r) for r in ref)
            for m in MARGINS:
                cells = []
                for h in HAMMING:
                    dets = res[(h, m)]
                    false = sum(
                        data.is_false(k, int(t), f[1:].reshape(4, 2))
                        for k, (ints, floats) in enumerate(dets)
                        for t, f in zip(ints[:, 0], floats, strict=True)
                    )
                    hits = sum(
                        len(set(ints[:, 0].tolist()) & r)
                        for (ints, _), r in zip(dets, ref, strict=True)
                    )
                    cells.append(f"{hits:>8d}/{false:<5d}")
                print(f"{name:13} {m:6g} " + " ".join(cells) + f" {present:7d}")
    finally:
        pool.terminate()  # the worker's exit status is not trusted (pupil-apriltags #46)


def _tagslam_cams(bag: Path, root: Path) -> dict[int, np.ndarray]:
    """TagSLAM's camera positions by stamp: the rig's odometry @ camera_poses.yaml."""
    from rosbags.highlevel import AnyReader

    from tagtrail.geometry.se3 import R_from_rotvec, T_from_xyz_quat, make_T

    cam = yaml.safe_load((root / "camera_poses.yaml").read_text())["cam0"]["pose"]
    rig_T_cam = make_T(
        R_from_rotvec([cam["rotation"][k] for k in "xyz"]), [cam["position"][k] for k in "xyz"]
    )
    out = {}
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.msgtype == "nav_msgs/msg/Odometry"]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            p = msg.pose.pose
            T = (
                T_from_xyz_quat(
                    [p.position.x, p.position.y, p.position.z],
                    [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w],
                )
                @ rig_T_cam
            )
            out[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec] = T[:3, 3]
    return out


def tagslam() -> None:
    from tagtrail.geometry.registration import umeyama
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.spec import load_pipeline
    from tagtrail.stages import REGISTRY

    print(
        f"\n{'recording':12} {'hamming 0/1/2':>15} {'max_hamming':>11} {'frames':>9} "
        f"{'vs TagSLAM mean mm':>18} {'p95 mm':>7}"
    )
    for test, size in (("1", 0.225), ("16", 0.16)):
        root = REALDATA / f"tagslam_test_{test}"
        with tempfile.TemporaryDirectory() as tmp:
            bag, ref = Path(tmp) / "tag_detections.bag", Path(tmp) / "reference.bag"
            bag.write_bytes(bz2.decompress((root / "tag_detections.bag.bz2").read_bytes()))
            ref.write_bytes(bz2.decompress((root / "reference.bag.bz2").read_bytes()))
            ref_cams = _tagslam_cams(ref, root)
            for h in (0, 2):
                (Path(tmp) / "pipeline.yaml").write_text(
                    yaml.safe_dump(
                        {
                            "datasets": {
                                "reference": {
                                    "source": str(bag),
                                    "camera": str(root / "cameras.yaml"),
                                }
                            },
                            "stages": {"pnp": {"tag_size": size}, "extract": {"max_hamming": h}},
                        }
                    )
                )
                runner = Runner(load_pipeline(Path(tmp) / "pipeline.yaml", REGISTRY))
                runner.run(["smooth"])
                keys = {s.stage: s.key for s in runner.plan(["smooth"])}
                det = runner.store.load("extract", keys["extract"], "detections")
                traj = runner.store.load("smooth", keys["smooth"], "trajectory")
                hist = "/".join(str(int((det["hamming"] == k).sum())) for k in range(3))
                common = [k for k, t in enumerate(traj["t_ns"]) if int(t) in ref_cams]
                p = traj[["x_m", "y_m", "z_m"]].to_numpy()[common]
                q = np.array([ref_cams[int(traj["t_ns"].iloc[k])] for k in common])
                s, R, t = umeyama(p, q, with_scale=False)
                err = np.linalg.norm(p @ R.T + t - q, axis=1) * 1e3
                print(
                    f"test {test:7} {hist:>15} {h:11d} {len(common):4d}/{len(ref_cams):<4d} "
                    f"{err.mean():18.1f} {np.percentile(err, 95):7.1f}"
                )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sets", default=",".join([*IMAGE_SETS, "tagslam"]))
    names = ap.parse_args().sets.split(",")
    image_names = [n for n in names if n in IMAGE_SETS]
    if image_names:
        print(
            "image sets: tags found / false detections per max_hamming (h0..h3), at "
            "min_decision_margin 20 (default) and 0"
        )
        images(image_names)
    if "tagslam" in names:
        tagslam()


if __name__ == "__main__":
    main()

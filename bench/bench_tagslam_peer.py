"""Benchmark (issue 15): tagtrail beside TagSLAM on TagSLAM's own recordings, and which of the
two trajectories is nearer the truth on a simulated copy of test 16 that has ground truth.

Part 1, real (``../shared/realdata/tagslam_test_{16,1}``): ``tagtrail init --reference
tag_detections.bag --camera cameras.yaml --tag-size S`` + ``tagtrail run`` (nothing else), then
each of tagtrail's default ``trajectory.csv`` (frames held in time by the motion prior) and
``trajectory_raw.csv`` (every frame on its own corners, what TagSLAM solves: it has no motion
model) against TagSLAM's trajectory (``reference.bag``; SE(3) fit on positions, frames matched
by stamp). Beside them, for each trajectory, the RMS of the positions' second differences in the
camera frame (x right, y down, z forward) and their lag-1 autocorrelation: independent per-frame
noise gives -0.67, smooth motion +0.25 or more.

Part 2, simulated (ground truth): test 16's scene rebuilt in the simulator -- TagSLAM's five
collinear tags (0.16 m), the real camera (1280x1024, radtan), TagSLAM's own stamps (10 Hz), and
as the true path TagSLAM's camera trajectory low-passed (Gaussian, sigma 0.3 s) -- detections
with Gaussian corner noise, optionally with hand shake added to the true path (white
acceleration of ``--shake`` m/s^2/sqrt(Hz), kept above 1 Hz). tagtrail's default and frames-alone
trajectories are compared with the truth and with each other, as in part 1.

Run: ``.venv/bin/python bench/bench_tagslam_peer.py [--noise 0.1,0.2] [--shake 0,0.12]
[--skip-real]``. Prints the tables (markdown).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tagtrail.cli import main as tagtrail  # noqa: E402
from tests.tagslam import (  # noqa: E402
    TAG_SIZES,
    agreement,
    matched,
    roughness,
    simulate_test_16,
    tagslam_reference,
    unpack,
)

REALDATA = REPO.parent / "shared" / "realdata"


def rough(T: np.ndarray) -> str:
    rms, ac = roughness(T)
    return " / ".join(f"{1e3 * r:.1f} ({c:+.2f})" for r, c in zip(rms, ac, strict=True))


def run_tagtrail(folder: Path, args: list[str]) -> tuple[Path, Path]:
    """``init`` + ``run`` in ``folder``; the default and frames-alone trajectory files."""
    cwd = Path.cwd()
    os.chdir(folder)
    try:
        with (
            open(os.devnull, "w") as null,
            contextlib.redirect_stdout(null),
            contextlib.redirect_stderr(null),
        ):
            assert tagtrail(["init", *args]) == 0
            assert tagtrail(["run"]) == 0
    finally:
        os.chdir(cwd)
    out = folder / "outputs/reference"
    return out / "trajectory.csv", out / "trajectory_raw.csv"


def row(name: str, T: np.ndarray, ref: np.ndarray) -> str:
    mean, mx, ang = agreement(T, ref)
    return f"| {name} | {1e3 * mean:.2f} / {1e3 * mx:.1f} | {ang:.3f} | {rough(T)} |"


HEAD = (
    "| trajectory | vs {ref}: mean / max (mm) | rot (deg) | 2nd differences x / y / z, "
    "RMS mm (lag-1 autocorr.) |\n|---|---|---|---|"
)


def real_part(tmp: Path) -> None:
    for name, size in TAG_SIZES.items():
        root, work = REALDATA / name, tmp / name
        work.mkdir()
        bag = unpack(root, "tag_detections.bag", work)
        _, cams = tagslam_reference(unpack(root, "reference.bag", work), root)
        default, raw = run_tagtrail(
            work,
            [
                "--reference",
                str(bag),
                "--camera",
                str(root / "cameras.yaml"),
                "--tag-size",
                str(size),
            ],
        )
        print(f"\n### {name} (real; TagSLAM is a peer, not ground truth)\n")
        print(HEAD.format(ref="TagSLAM"))
        T, ref = matched(default, cams)
        print(row("tagtrail default (`trajectory.csv`)", T, ref))
        T, ref = matched(raw, cams)
        print(row("tagtrail frames alone (`trajectory_raw.csv`)", T, ref))
        print(f"| TagSLAM | 0 | 0 | {rough(ref)} |")


def sim_part(tmp: Path, noises: list[float], shakes: list[float], seed: int) -> None:
    print(
        "\n### tagslam_test_16 simulated (ground truth: TagSLAM's path low-passed, its stamps, "
        "its tags and camera)\n"
    )
    print(
        "| corner noise (px) | shake (m/s^2/sqrt(Hz)) | trajectory | vs truth: mean / max (mm) "
        "| rot (deg) | 2nd differences x / y / z, RMS mm (lag-1 autocorr.) | "
        "default vs frames alone: mean (mm) |\n|---|---|---|---|---|---|---|"
    )
    for noise in noises:
        for density in shakes:
            work = tmp / f"sim_{noise}_{density}"
            bag, truth = simulate_test_16(REALDATA, work, noise, density, seed)
            default, raw = run_tagtrail(
                work, ["--reference", str(bag), "--tag-size", str(TAG_SIZES["tagslam_test_16"])]
            )
            Td, ref = matched(default, truth)
            Tr, _ = matched(raw, truth)
            between = agreement(Td, Tr)[0]
            for label, T in (("default", Td), ("frames alone", Tr), ("truth", ref)):
                mean, mx, ang = agreement(T, ref)
                extra = f"{1e3 * between:.2f}" if label == "default" else ""
                print(
                    f"| {noise} | {density} | {label} | {1e3 * mean:.2f} / {1e3 * mx:.1f} | "
                    f"{ang:.3f} | {rough(T)} | {extra} |"
                )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--noise", default="0.1,0.2", help="corner noise levels (px), comma-separated")
    ap.add_argument("--shake", default="0,0.12", help="hand shake densities, comma-separated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-real", action="store_true")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-tagslam-") as d:
        tmp = Path(d)
        if not a.skip_real:
            real_part(tmp)
        sim_part(
            tmp,
            [float(x) for x in a.noise.split(",")],
            [float(x) for x in a.shake.split(",")],
            a.seed,
        )


if __name__ == "__main__":
    main()

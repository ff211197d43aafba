"""TagSLAM's own recordings (``../shared/realdata/tagslam_test_{1,16}``) set up the way a
TagSLAM user would -- ``tagtrail init --reference tag_detections.bag --camera cameras.yaml
--tag-size S`` and ``tagtrail run``, nothing else -- against TagSLAM's trajectory in its
``reference.bag`` (a peer, not ground truth: SE(3) fit on the positions, frames matched by
stamp).

Measured when written (issue 15's targets in brackets): every frame posed; the default
trajectory 5.7 mm / 0.10 deg mean from TagSLAM's on test 16 [1 mm / 0.05 deg] and 12.8 mm on
test 1 [8 mm]; the frames on their corners alone (``trajectory.motion: none``, what TagSLAM
solves: it has no motion model) 0.44 mm / 0.02 deg and 8.2 mm. The gap is the motion prior: it
moves test 16's frames by 4.4 mm median, within their own 3.6 mm standard deviation (corner
noise as the residuals show it), so the prior is not overruling the evidence -- two per-frame
solvers on the same corners simply agree far better than either is accurate. Which of the two
is closer to the truth these recordings cannot tell.
"""

from __future__ import annotations

import bz2
from pathlib import Path

import numpy as np
import pytest

from tagtrail.geometry.registration import umeyama
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.io.layouts import read_trajectory
from tests.stages.test_survey import _poses, _tagslam_reference

CASES = {  # name: (tag size m, default trajectory mm / deg, frames alone mm / deg) bounds
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
    posed, pos, ang = _agreement(tmp_path / "outputs/reference/trajectory.csv", cams)
    assert main(["run", "-S", "trajectory.motion=none"]) == 0
    _, pos_a, ang_a = _agreement(tmp_path / "outputs/reference/trajectory_raw.csv", cams)
    print(f"\n{name}: {posed:.0%} of TagSLAM's frames posed; default {1e3 * pos:.2f} mm / "
          f"{ang:.3f} deg, frames alone {1e3 * pos_a:.2f} mm / {ang_a:.3f} deg")
    assert posed >= 0.95
    assert 1e3 * pos <= d_mm and ang <= d_deg
    assert 1e3 * pos_a <= a_mm and ang_a <= a_deg

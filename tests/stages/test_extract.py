"""Stage extract on real photos: bags built in tmp_path, image folders, detection bags."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pydantic
import pytest

from tagtrail.errors import SourceError
from tagtrail.io.camera_files import read_camera_file
from tagtrail.stages import extract
from tests.extracting import extract_from
from tests.io import bags

T0 = bags.T0_NS
DT = 33_333_333
FRAME_COLS = ["t_ns", "frame_idx", "n_det", "timed"]
DET_COLS = [
    "t_ns",
    "frame_idx",
    "tag_id",
    "hamming",
    "decision_margin",
    "c0x",
    "c0y",
    "c1x",
    "c1y",
    "c2x",
    "c2y",
    "c3x",
    "c3y",
]
OBS_COLS = ["t_ns", "frame_idx", "tag_id", "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]


@pytest.fixture(scope="module")
def upenn_dir(realdata: Path) -> Path:
    return realdata / "upenn_ar_tag36h11_id12_seq"


@pytest.fixture(scope="module")
def upenn_bag(upenn_dir: Path, tmp_path_factory) -> Path:
    """All 93 frames as CompressedImage (their JPEG bytes) + CameraInfo, sqlite3."""
    cam = read_camera_file(upenn_dir / "frames/camera.yaml")
    files = sorted((upenn_dir / "frames").glob("frame*.jpg"))
    out = [("/cam/camera_info", T0, bags.camera_info_msg(cam))]
    out += [
        (
            "/cam/image/compressed",
            T0 + k * DT,
            bags.compressed_msg(f.read_bytes(), "jpeg", T0 + k * DT),
        )
        for k, f in enumerate(files)
    ]
    return bags.write_bag(tmp_path_factory.mktemp("upenn") / "bag", out, "sqlite3")


@pytest.fixture(scope="module")
def upenn_bag_out(upenn_bag: Path) -> dict:
    return extract_from(upenn_bag, extract.Params())


@pytest.fixture(scope="module")
def upenn_unrefined(upenn_bag: Path) -> dict:
    """The detector's own corners (``refit_corners: false``)."""
    return extract_from(upenn_bag, extract.Params(refit_corners=False))


def check_tables(out: dict) -> None:
    assert set(out) == {"frames", "detections", "camera", "observations", "odometry", "mount"}
    assert list(out["frames"].columns) == FRAME_COLS
    assert list(out["detections"].columns) == DET_COLS
    assert list(out["observations"].columns) == OBS_COLS
    assert out["frames"].dtypes.tolist() == [np.int64, np.int32, np.int32, np.bool_]
    assert out["detections"].dtypes.tolist()[:4] == [np.int64, np.int32, np.int32, np.int32]
    det = out["detections"]
    assert (det.sort_values(["frame_idx", "tag_id"], kind="stable").index == det.index).all()


def test_upenn_corners_match_expected_minus_half_pixel(upenn_unrefined: dict, upenn_dir) -> None:
    """The detector's own corners (no re-fit) are a peer detector's minus half a pixel."""
    out = upenn_unrefined
    check_tables(out)
    det = out["detections"]
    assert len(out["frames"]) == 93 and (out["frames"]["n_det"] == 1).all()
    assert out["frames"]["timed"].all()  # a bag: its header stamps are capture times
    assert (det["tag_id"] == 12).all() and (det["hamming"] == 0).all()
    assert det["t_ns"].tolist() == [T0 + k * DT for k in range(93)]
    expected = np.load(upenn_dir / "corners.npy")  # a peer detector, C-library pixel convention
    offset = expected - det[DET_COLS[5:]].to_numpy().reshape(-1, 4, 2)
    # measured: mean (+0.499, +0.503) px, median (+0.498, +0.500) px, max |offset - 0.5| 0.31 px
    np.testing.assert_allclose(np.median(offset.reshape(-1, 2), axis=0), [0.5, 0.5], atol=0.02)
    assert np.abs(offset - 0.5).max() < 0.35
    assert out["camera"].same_as(read_camera_file(upenn_dir / "frames/camera.yaml"))


def test_upenn_refit_moves_real_corners_by_a_fraction_of_a_pixel(
    upenn_bag_out: dict, upenn_unrefined: dict
) -> None:
    """On real photos (jpeg, real blur and lens) the re-fit keeps every tag, in the same frames,
    and moves corners by a fraction of a pixel (accuracy itself: tests/io/test_corners.py)."""
    refit, raw = upenn_bag_out, upenn_unrefined
    check_tables(refit)
    for col in ("t_ns", "frame_idx", "tag_id"):
        assert refit["detections"][col].tolist() == raw["detections"][col].tolist()
    shift = np.linalg.norm(
        (
            refit["detections"][DET_COLS[5:]].to_numpy()
            - raw["detections"][DET_COLS[5:]].to_numpy()
        ).reshape(-1, 4, 2),
        axis=2,
    )
    print(
        f"\nupenn re-fit shift: median {np.median(shift):.3f} px, max {shift.max():.3f} px, "
        f"{np.mean(shift.max(axis=1) > 0):.0%} of tags re-fitted"
    )
    assert np.mean(shift.max(axis=1) > 0) > 0.9  # re-fitted, not skipped
    assert np.median(shift) < 0.3 and shift.max() <= 1.0


def test_rgb8_mcap_bag_and_folder_agree(upenn_bag_out: dict, upenn_dir, tmp_path) -> None:
    files = sorted((upenn_dir / "frames").glob("frame*.jpg"))[:6]
    cam = read_camera_file(upenn_dir / "frames/camera.yaml")
    out = [("/camera/camera_info", T0, bags.camera_info_msg(cam))]
    for k, f in enumerate(files):
        rgb = np.ascontiguousarray(cv2.imread(str(f))[..., ::-1])
        out.append(("/camera/image_raw", T0 + k * DT, bags.image_msg(rgb, "rgb8", T0 + k * DT)))
    raw = extract_from(bags.write_bag(tmp_path / "bag", out), extract.Params(chunk_size=2))
    ref = upenn_bag_out["detections"].iloc[:6].reset_index(drop=True)
    assert raw["detections"]["tag_id"].tolist() == [12] * 6
    # rgb8 → gray (cvtColor) differs slightly from JPEG's own gray decoding
    np.testing.assert_allclose(raw["detections"][DET_COLS[5:]], ref[DET_COLS[5:]], atol=0.15)
    folder = tmp_path / "frames"
    folder.mkdir()
    for f in [*files, upenn_dir / "frames/camera.yaml"]:
        shutil.copy(f, folder / f.name)
    cv2.imwrite(str(folder / "frame0006.png"), np.full((480, 640), 255, np.uint8))  # no tag
    got = extract_from(folder, extract.Params(workers=1, chunk_size=4))
    assert got["frames"]["n_det"].tolist() == [1] * 6 + [0]  # frames without tags are kept
    assert got["frames"]["t_ns"].tolist() == [k * 100_000_000 for k in range(7)]
    pd.testing.assert_frame_equal(
        got["detections"].drop(columns="t_ns"), ref.drop(columns="t_ns")
    )  # same JPEG bytes, same result


@pytest.mark.slow  # 72 real photos (~3 s): make test-all
def test_swatbotics_ids_vs_groundtruth(realdata: Path) -> None:
    folder = realdata / "swatbotics_mapping_feb_2014"
    out = extract_from(folder / "images", extract.Params())
    check_tables(out)
    files = sorted(p.name for p in (folder / "images").glob("*.JPG"))
    truth = {
        ln.split()[0]: set(map(int, ln.split()[1:]))
        for ln in (folder / "groundtruth.txt").read_text().splitlines()
        if ln.strip()
    }
    det = out["detections"]
    found = {files[i]: set(det.loc[det["frame_idx"] == i, "tag_id"]) for i in range(len(files))}
    tp = sum(len(found[f] & truth[f]) for f in files)
    fp = sum(len(found[f] - truth[f]) for f in files)
    exact = sum(found[f] == truth[f] for f in files)
    # measured (quad_decimate 2, min_decision_margin 20): 216 of 236 found, 0 false, 60/72 exact
    assert fp == 0 and tp >= 210 and exact >= 58
    assert set(det["tag_id"]) == set(range(20))
    assert det["decision_margin"].min() >= 20.0


def test_detection_bag_humble_sqlite3(upenn_dir: Path, tmp_path: Path) -> None:
    cam = read_camera_file(upenn_dir / "frames/camera.yaml")
    corners = np.load(upenn_dir / "corners.npy")[:5]  # as apriltag_ros would publish them
    out = [("/camera_info", T0, bags.camera_info_msg(cam))]
    for k, c in enumerate(corners):
        dets = [(12, 0, 90.0, c), (7, 1, 90.0, c + 50), (5, 0, 10.0, c + 100)]
        out.append(("/detections", T0 + k * DT, bags.detections_msg(T0 + k * DT, dets)))
    out.append(
        (
            "/detections",
            T0 + 9 * DT,
            bags.detections_msg(T0 + 9 * DT, [(12, 0, 90.0, corners[0])], family="tag25h9"),
        )
    )
    bag = bags.make_humble(bags.write_bag(tmp_path / "bag", out, "sqlite3"))
    assert extract_from(bag)["frames"]["n_det"].tolist() == [2] * 5 + [0]  # hamming 1 kept
    got = extract_from(bag, extract.Params(max_hamming=0))
    check_tables(got)
    det = got["detections"]
    assert got["frames"]["n_det"].tolist() == [1] * 5 + [0]  # hamming 1, margin 10, 25h9 dropped
    np.testing.assert_allclose(det[DET_COLS[5:]].to_numpy().reshape(-1, 4, 2), corners - 0.5)
    assert det["t_ns"].tolist() == [T0 + k * DT for k in range(5)]  # exact int64 ns
    assert got["camera"].same_as(cam)
    loose = extract_from(bag, extract.Params(max_hamming=1, min_decision_margin=5, tag_ids=(5, 12)))
    assert loose["detections"]["tag_id"].tolist() == [5, 12] * 5


def test_observations_source(tmp_path: Path) -> None:
    (tmp_path / "observations.csv").write_text(
        "stamp_sec,stamp_nanosec,tag,x,y,z,qx,qy,qz,qw\n"
        "1,0,tag36h11:4,0.1,0.2,1.5,0,0,0,1\n1,0,tag36h11:2,0.0,0.1,2.0,1,0,0,0\n"
        "2,0,tag36h11:4,0.1,0.2,1.4,0,0,0,1\n"
    )
    out = extract_from(tmp_path, extract.Params())
    check_tables(out)
    assert out["camera"] is None and len(out["detections"]) == 0
    assert out["frames"].values.tolist() == [[10**9, 0, 2, True], [2 * 10**9, 1, 1, True]]
    obs = out["observations"]
    assert obs["tag_id"].tolist() == [2, 4, 4] and obs["z_m"].tolist() == [2.0, 1.5, 1.4]


def test_worker_count_and_chunking_do_not_change_output(upenn_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "f"
    folder.mkdir()
    for f in sorted((upenn_dir / "frames").glob("*"))[:8]:
        shutil.copy(f, folder / f.name)
    a = extract_from(folder, extract.Params(workers=1, chunk_size=8))
    b = extract_from(folder, extract.Params(workers=2, chunk_size=1))
    for k in ("frames", "detections", "observations"):
        pd.testing.assert_frame_equal(a[k], b[k])
    with pytest.raises(
        SourceError,
        match=r"\(7 images\): no detection is left: tag_ids \[3\] "
        r"drops 7 of 7 detections; set extract.tag_ids: null",
    ):
        extract_from(folder, extract.Params(tag_ids=(3,)))
    c = extract_from(folder, extract.Params(tag_ids=(3, 12)))
    pd.testing.assert_frame_equal(c["detections"], a["detections"])


def test_params_and_missing_camera(upenn_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(pydantic.ValidationError):
        extract.Params(family="tag25h9")  # fixed: tag36h11
    with pytest.raises(pydantic.ValidationError):
        extract.Params(max_hamming=4)
    shutil.copy(upenn_dir / "frames/frame0000.jpg", tmp_path / "a.jpg")
    with pytest.raises(SourceError, match="no camera intrinsics .* `camera: <camera_info.yaml>`"):
        extract_from(tmp_path, extract.Params())


def test_undecodable_frame_names_the_file(upenn_dir: Path, tmp_path: Path) -> None:
    for f in ("frame0000.jpg", "camera.yaml"):
        shutil.copy(upenn_dir / "frames" / f, tmp_path / f)
    (tmp_path / "frame0001.jpg").write_bytes(b"truncated")
    with pytest.raises(SourceError, match=r"frame0001.jpg: cannot read image"):
        extract_from(tmp_path, extract.Params(workers=1))


SCRIPT = """
import sys
import cv2
from tagtrail.vision.apriltag import detect
from tagtrail.io.sources import open_source
from tagtrail.schemas.pipeline import DatasetConfig
from tagtrail.stages import extract

def main():
    with open_source(DatasetConfig(source=sys.argv[1])) as src:
        out = extract.run(src, extract.Params(workers=1))
    # and a detector in this very process, alive until exit (the guarded teardown path)
    img = cv2.imread(sys.argv[1] + "/frame0000.jpg", cv2.IMREAD_GRAYSCALE)
    ints, _ = detect(img, extract.Params(min_decision_margin=0).detector())
    print(len(out["detections"]), len(ints))
"""


@pytest.mark.slow
def test_repeated_runs_in_subprocesses_always_exit_0(upenn_dir: Path, tmp_path: Path) -> None:
    """pupil-apriltags can segfault at interpreter exit (pupil-labs/apriltags#46): 20 runs."""
    for f in ("frame0000.jpg", "frame0001.jpg", "camera.yaml"):
        shutil.copy(upenn_dir / "frames" / f, tmp_path / f)
    script = tmp_path / "run_extract.py"
    script.write_text(SCRIPT + "\nmain()\n")  # no `if __name__ == "__main__"` guard needed
    codes, outs = [], []
    for _ in range(10):  # two at a time: the machine has 2 cores
        procs = [
            subprocess.Popen(
                [sys.executable, str(script), str(tmp_path)],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for _ in range(2)
        ]
        for p in procs:
            out, err = p.communicate(timeout=120)
            codes.append(p.returncode)
            outs.append(out.strip() or err[-500:])
    assert codes == [0] * 20, outs
    assert set(outs) == {"2 1"}


# --- frames of another size than the camera's: left out (a warning naming them), or an error ---


def upenn_folder(upenn_dir: Path, folder: Path, resize: tuple[int, ...]) -> Path:
    """The first 10 upenn frames (640x480) + camera.yaml; frames ``resize`` scaled to 1280x960."""
    folder.mkdir()
    shutil.copy(upenn_dir / "frames/camera.yaml", folder)
    for k, f in enumerate(sorted((upenn_dir / "frames").glob("frame*.jpg"))[:10]):
        img = cv2.imread(str(f))
        cv2.imwrite(str(folder / f.name), cv2.resize(img, (1280, 960)) if k in resize else img)
    return folder


def test_folder_frames_of_another_size_are_left_out(
    upenn_dir, tmp_path, monkeypatch, caplog, capsys
) -> None:
    from tagtrail.cli import main

    monkeypatch.chdir(tmp_path)
    folder = upenn_folder(upenn_dir, tmp_path / "imgs", resize=(5,))
    assert main(["init", "--reference", "imgs", "--tag-size", "0.14"]) == 0
    with caplog.at_level("WARNING"):
        assert main(["run"]) == 0
    warned = [r.getMessage() for r in caplog.records if "left out" in r.getMessage()]
    assert warned == [
        f"image folder {folder} (10 images): 1 of 10 frames left out, their size "
        f"is not the camera's 640x480 ({folder / 'camera.yaml'}): "
        "frame0005.jpg (1280x960)"
    ]
    raw = pd.read_csv(tmp_path / "outputs/reference/trajectory_raw.csv")
    assert raw["stamp_nanosec"].tolist() == [k * 100_000_000 for k in range(10) if k != 5]
    xyz = raw[["x", "y", "z"]].to_numpy()  # a hand-held camera barely moving: no outlier
    assert np.linalg.norm(xyz - np.median(xyz, axis=0), axis=1).max() < 0.005


def test_folder_of_wrong_size_frames_stops_with_one_line(
    upenn_dir, tmp_path, monkeypatch, capsys
) -> None:
    from tagtrail.cli import main

    monkeypatch.chdir(tmp_path)
    folder = upenn_folder(upenn_dir, tmp_path / "imgs", resize=tuple(range(10)))
    assert main(["init", "--reference", "imgs", "--tag-size", "0.14"]) == 0
    capsys.readouterr()
    assert main(["run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert (
        f"{folder}: no frame has the size 640x480 of the camera ({folder / 'camera.yaml'}), "
        "they are 1280x960 (10 frames); give the camera calibration"
    ) in err[0]
    assert not (tmp_path / "outputs/reference/trajectory_raw.csv").exists()


@pytest.mark.parametrize("compressed", [False, True])
def test_bag_frames_of_another_size_are_left_out(
    upenn_dir, tmp_path, caplog, compressed: bool
) -> None:
    """Image / CompressedImage messages whose decoded size is not CameraInfo's: the same rule."""
    files = sorted((upenn_dir / "frames").glob("frame*.jpg"))[:4]
    cam = read_camera_file(upenn_dir / "frames/camera.yaml")

    def bag(name: str, small: set[int]) -> Path:
        out = [("/camera/camera_info", T0, bags.camera_info_msg(cam))]
        for k, f in enumerate(files):
            img = cv2.imread(str(f))
            img = cv2.resize(img, (320, 240)) if k in small else img
            t = T0 + k * DT
            rgb = np.ascontiguousarray(img[..., ::-1])
            msg = (
                bags.compressed_msg(cv2.imencode(".png", img)[1].tobytes(), "png", t)
                if compressed
                else bags.image_msg(rgb, "rgb8", t)
            )
            out.append(("/camera/image" + "/compressed" * compressed, t, msg))
        return bags.write_bag(tmp_path / name, out)

    with caplog.at_level("WARNING"):
        got = extract_from(bag("some", {2}), extract.Params(chunk_size=2))
    assert got["frames"]["frame_idx"].tolist() == [0, 1, 3]
    assert got["detections"]["frame_idx"].tolist() == [0, 1, 3]
    msg = [r.getMessage() for r in caplog.records if "left out" in r.getMessage()]
    assert len(msg) == 1 and msg[0].endswith(
        f"1 of 4 frames left out, their size is not the camera's 640x480 (CameraInfo of "
        f"/camera/camera_info): frame 2 at {(T0 + 2 * DT) // 10**9}.{(T0 + 2 * DT) % 10**9:09d} s "
        "(320x240)"
    )
    with pytest.raises(
        SourceError,
        match=r"no frame has the size 640x480 of the camera "
        r"\(CameraInfo of /camera/camera_info\), they are 320x240 \(4 frames\)",
    ):
        extract_from(bag("all", {0, 1, 2, 3}), extract.Params())

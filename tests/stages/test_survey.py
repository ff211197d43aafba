"""A surveyed world (``optimize.survey``) on real data: TagSLAM test 16's ``tagslam.yaml`` gives
TagSLAM's world frame (checked against the tag poses and trajectory in its ``reference.bag``),
the WPILib layout puts the FRC field photos' map in the field frame; bad files are one line."""

from __future__ import annotations

import bz2
import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from tagtrail.errors import DataError, SpecError
from tagtrail.geometry.registration import umeyama
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import rotation_angle
from tagtrail.runner.spec import load_pipeline
from tagtrail.schemas.artifacts import POSE_COLS
from tagtrail.stages import REGISTRY, optimize
from tests.stages.pipelines import artifact as _artifact
from tests.stages.pipelines import pipeline_file as _pipeline
from tests.stages.pipelines import run_stages as _run
from tests.tagslam import poses as _poses
from tests.tagslam import tagslam_reference as _tagslam_reference


def test_tagslam_yaml_reproduces_tagslams_world_on_test_16(
    realdata: Path, tmp_path: Path, caplog
) -> None:
    """Test 16 names one known tag (2, on the static body 'lab'): with it, tagtrail's map is in
    TagSLAM's world -- each tag within 0.1 mm / 0.02 deg of TagSLAM's -- and the trajectory
    needs no fit to TagSLAM's (the best rigid fit is within 0.05 deg / 3 mm of the identity).
    Without the survey the map sits in the anchor tag's frame, a metre away."""
    root = realdata / "tagslam_test_16"
    bag = tmp_path / "tag_detections.bag"
    bag.write_bytes(bz2.decompress((root / "tag_detections.bag.bz2").read_bytes()))
    ref_bag = tmp_path / "reference.bag"
    ref_bag.write_bytes(bz2.decompress((root / "reference.bag.bz2").read_bytes()))
    ref_tags, ref_cams = _tagslam_reference(ref_bag, root)
    dataset = f"{{source: {bag}, camera: {root / 'cameras.yaml'}}}"
    survey = {"file": str(root / "tagslam.yaml")}
    plain = _run(_pipeline(tmp_path, dataset, {"pnp": {"tag_size": 0.16}}), "optimize")
    with caplog.at_level(logging.INFO, logger="tagtrail.stages.optimize"):
        runner = _run(
            _pipeline(
                tmp_path, dataset, {"pnp": {"tag_size": 0.16}, "optimize": {"survey": survey}}
            ),
            "smooth",
        )
    assert (
        "surveyed world (" in caplog.text and "from known tags [2]: residuals 0.0 mm" in caplog.text
    )
    tags = _artifact(runner, "optimize", "tag_map")
    assert sorted(tags["tag_id"]) == sorted(ref_tags) == [0, 1, 2, 3, 4]
    T = _poses(tags)
    ref = np.array([ref_tags[int(i)] for i in tags["tag_id"]])
    assert np.linalg.norm(T[:, :3, 3] - ref[:, :3, 3], axis=1).max() < 1e-4
    assert np.degrees(geodesic_angle(T[:, :3, :3], ref[:, :3, :3])).max() < 0.02
    before = _poses(_artifact(plain, "optimize", "tag_map"))
    assert np.linalg.norm(before[:, :3, 3] - ref[:, :3, 3], axis=1).min() > 0.5

    traj = _artifact(runner, "smooth", "trajectory")
    stamps = traj["t_ns"].to_numpy()
    common = [k for k, s in enumerate(stamps) if int(s) in ref_cams]
    assert len(common) >= 0.95 * len(ref_cams)
    p = _poses(traj)[common, :3, 3]
    p_ref = np.array([ref_cams[int(stamps[k])][:3, 3] for k in common])
    _, R, t = umeyama(p, p_ref, with_scale=False)
    assert np.degrees(rotation_angle(R)) < 0.05 and np.linalg.norm(t) < 0.003
    print(
        f"\ntest 16 surveyed world: tags within "
        f"{1e3 * np.linalg.norm(T[:, :3, 3] - ref[:, :3, 3], axis=1).max():.3f} mm of "
        f"TagSLAM's; trajectory vs TagSLAM's without a fit: "
        f"{1e3 * np.linalg.norm(p - p_ref, axis=1).mean():.1f} mm mean; best fit "
        f"{np.degrees(rotation_angle(R)):.3f} deg / {1e3 * np.linalg.norm(t):.2f} mm"
    )


def _layout(path: Path) -> dict[int, np.ndarray]:
    doc = json.loads(path.read_text())
    return {t["ID"]: np.array([t["pose"]["translation"][k] for k in "xyz"]) for t in doc["tags"]}


def test_field_layout_puts_the_field_photos_map_in_the_field_frame(
    realdata: Path, tmp_path: Path
) -> None:
    """The FRC photos map tags 3 and 4 together (the other tags are seen in separate groups);
    with the WPILib layout of all 16 tags they land in the field frame: the residuals at the
    known tags (position and orientation, the layout's +X-out-of-the-face frame turned to SPEC's)
    are those of single-view photos on an approximate calibration, a few mm and ~1 deg."""
    root = realdata / "photonvision_frc2024_field"
    layout_file = root / "2024-crescendo.json"
    dataset = f"{{source: {root / 'images'}}}"
    plain = _run(_pipeline(tmp_path, dataset, {"pnp": {"tag_size": 0.1651}}), "optimize")
    local = _artifact(plain, "optimize", "tag_map")
    stages = {"pnp": {"tag_size": 0.1651}, "optimize": {"survey": {"file": str(layout_file)}}}
    runner = _run(_pipeline(tmp_path, dataset, stages), "smooth")
    tags = _artifact(runner, "optimize", "tag_map")
    assert sorted(tags["tag_id"]) == sorted(local["tag_id"]) == [3, 4]
    layout = _layout(layout_file)
    err = [
        np.linalg.norm(p - layout[int(i)])
        for i, p in zip(tags["tag_id"], tags[["x_m", "y_m", "z_m"]].to_numpy(), strict=True)
    ]
    assert max(err) < 0.01, err
    assert np.linalg.norm(local[["x_m", "y_m", "z_m"]].to_numpy(), axis=1).max() < 1  # anchor 3
    # the residuals at the known tags, as the stage computes (and logs) them
    params = optimize.Params(survey={"file": str(layout_file)})
    assert params.survey is not None
    moved, block = optimize.surveyed_world(local, params.survey)
    pd.testing.assert_frame_equal(moved, tags)
    assert block["tags"] == [3, 4] and block["format"] == "wpilib" and block["model"] == "rigid"
    assert len(block["missing"]) == 14 and block["res_pos_max_m"] < 0.01
    assert 0.1 < block["res_rot_rms_deg"] < 2.0  # single photos, an approximate calibration
    report = _artifact(runner, "optimize", "report")  # the residuals, in the run's report
    assert report.survey is not None and report.survey.tags == [3, 4]
    assert report.survey.res_pos_max_m == pytest.approx(block["res_pos_max_m"])
    assert [t.tag_id for t in report.survey.per_tag] == [3, 4]
    traj = _artifact(runner, "smooth", "trajectory")
    cams = traj[["x_m", "y_m", "z_m"]].to_numpy()
    # the photos were taken on the field, in front of the speaker wall's tags (x = 16.58 m),
    # from a camera ~0.76 m (29.75 in) above the floor
    assert ((cams[:, 0] > 10) & (cams[:, 0] < 16.58)).all()
    assert np.abs(cams[:, 2] - 0.76).max() < 0.25
    with pytest.raises(DataError, match=r"a similarity needs 3 or more known tags"):
        optimize.surveyed_world(local, params.survey.model_copy(update={"model": "similarity"}))


def test_position_only_and_inline_known_tags(tmp_path: Path) -> None:
    """Inline known tags (tape-measured positions) over a file's; ``use`` picks ids."""
    tag_map = pd.DataFrame({"tag_id": [1, 2, 3, 4]})
    tag_map[POSE_COLS] = [
        [0, 0, 0, 0, 0, 0, 1],
        [1, 0, 0, 0, 0, 0, 1],
        [0, 1, 0, 0, 0, 0, 1],
        [1, 1, 0.5, 0, 0, 0, 1],
    ]
    tag_map["size_m"] = 0.16
    tag_map["std_pos_m"] = 0.001
    survey = {
        "tags": {
            1: {"position": [10, 0, 0]},
            2: {"position": [10, 1, 0]},
            3: {"position": [9, 0, 0]},
        }
    }
    params = optimize.Params(survey=survey)
    assert params.survey is not None
    moved, block = optimize.surveyed_world(tag_map, params.survey)
    assert block["res_pos_max_m"] < 1e-9 and block["res_rot_rms_deg"] is None
    assert np.allclose(moved.loc[3, ["x_m", "y_m", "z_m"]], [9, 1, 0.5])
    two = optimize.Params(survey={**survey, "use": [1, 2]})
    assert two.survey is not None
    with pytest.raises(DataError, match=r"position-only known tags \[1, 2\] do not fix"):
        optimize.surveyed_world(tag_map, two.survey)


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("layout.json", '{"tags": [{"ID": 1}]}', r"layout.json: tags\[0\]: expected \{ID, pose"),
        (
            "layout.json",
            '{"tags": [',
            r"layout.json: cannot read the known-poses file: Expecting value",
        ),
        (
            "tagslam.yaml",
            "bodies:\n - rig: {is_static: false}\n",
            r"tagslam.yaml: no tag with a pose on a static body",
        ),
        ("cameras.yaml", "cam0: {intrinsics: [1, 1, 1, 1]}\n", r"cameras.yaml: not a known-poses"),
        ("absent.yaml", None, r"absent.yaml: known-poses file not found"),
    ],
)
def test_bad_known_pose_files_are_one_line(
    tmp_path: Path, name: str, text: str | None, message: str
) -> None:
    bag_dir = tmp_path / "imgs"
    bag_dir.mkdir()
    (bag_dir / "a.png").write_bytes(b"")
    if text is not None:
        (tmp_path / name).write_text(text)
    path = _pipeline(
        tmp_path, f"{{source: {bag_dir}}}", {"optimize": {"survey": {"file": str(tmp_path / name)}}}
    )
    with pytest.raises(SpecError, match=message) as err:
        load_pipeline(path, REGISTRY)
    assert "\n" not in str(err.value)


def test_a_relative_survey_file_is_taken_from_the_pipeline_folder(
    realdata: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As the datasets' sources are: `tagtrail -p lab/pipeline.yaml run` from anywhere."""
    import shutil

    from tagtrail.errors import SpecError as Spec

    lab = tmp_path / "lab"
    lab.mkdir()
    shutil.copy(realdata / "photonvision_frc2024_field" / "2024-crescendo.json", lab / "field.json")
    (lab / "pipeline.yaml").write_text(
        yaml.safe_dump(
            {
                "datasets": {"reference": {"source": "images"}},
                "stages": {"optimize": {"survey": {"file": "field.json"}}},
            }
        )
    )
    monkeypatch.chdir(tmp_path)  # not the pipeline's folder
    pipe = load_pipeline(lab / "pipeline.yaml", REGISTRY, check_sources=False)
    survey = pipe.params_for("optimize", "reference").survey  # type: ignore[attr-defined]
    assert survey.format == "wpilib" and len(survey.known) == 16 and survey.file == "field.json"
    (lab / "field.json").unlink()
    with pytest.raises(Spec, match="field.json"):
        load_pipeline(lab / "pipeline.yaml", REGISTRY, check_sources=False)


def test_a_surveyed_world_places_every_part_of_the_tag_graph(
    realdata: Path, tmp_path: Path
) -> None:
    """The FRC photos see the field's tags in groups never seen together ({3, 4}, {2}, {5},
    {12}, {15}, and 6-10, one group or two depending on the corners); with
    ``edges.on_disconnected: keep`` each group is solved on its own and placed by its known
    tags, so every tag the photos see is in the field frame and every photo is posed there
    (without the survey only the anchor's group is mapped). A group of one tag sits at its
    known pose; the others' positions are as good as single photos from 3-6 m on an
    approximate calibration make them (measured: 3.6 mm for {3, 4}, 28-70 mm for {7..10}; 24-141
    mm for {6..10} with the corner re-fit before 3359fca)."""
    root = realdata / "photonvision_frc2024_field"
    layout_file = root / "2024-crescendo.json"
    dataset = f"{{source: {root / 'images'}}}"
    stages = {
        "pnp": {"tag_size": 0.1651},
        "edges": {"on_disconnected": "keep"},
        "optimize": {"survey": {"file": str(layout_file)}},
    }
    runner = _run(_pipeline(tmp_path, dataset, stages), "smooth")
    tags = _artifact(runner, "optimize", "tag_map")
    seen = [2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 15]
    assert sorted(tags["tag_id"]) == seen
    layout = _layout(layout_file)
    err = {
        int(i): float(np.linalg.norm(p - layout[int(i)]))
        for i, p in zip(tags["tag_id"], tags[["x_m", "y_m", "z_m"]].to_numpy(), strict=True)
    }
    print(f"\nposition error per tag (mm): { {k: round(1e3 * v, 1) for k, v in err.items()} }")
    assert max(err[3], err[4]) < 0.01 and max(err.values()) < 0.2, err
    report = _artifact(runner, "optimize", "report")
    assert report.survey is not None and report.survey.tags == [3, 4]
    groups = [tuple(report.survey.tags)] + [tuple(c.tags) for c in report.components]
    assert sorted(t for g in groups for t in g) == seen  # each tag in one group
    assert {(2,), (5,), (12,), (15,)} <= set(groups)
    assert all(c.survey is not None and c.survey.res_pos_max_m < 0.2 for c in report.components)
    traj = _artifact(runner, "smooth", "trajectory")
    assert len(traj) == 15  # every photo
    without = _run(_pipeline(tmp_path, dataset, {**stages, "optimize": {}}), "optimize")
    assert sorted(_artifact(without, "optimize", "tag_map")["tag_id"]) == [3, 4]

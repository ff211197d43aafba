"""``tagtrail init --survey FILE``: the known-poses file named in the pipeline it writes
(``optimize.survey.file``, and ``pnp.tag_sizes_from`` when it gives sizes), relative to the
pipeline's folder; ``run`` then maps in that world with those sizes."""

from __future__ import annotations

import bz2
import shutil
from pathlib import Path

import pytest
import yaml

from tagtrail.cli import main
from tests.cli_helpers import one_error_line
from tests.stages.pipelines import artifact as _artifact


def test_init_survey_tagslam_yaml_then_run(
    realdata: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    """Test 16's ``tagslam.yaml`` (tag 2 known, 0.16 m tags) given to init with no
    ``--tag-size`` (pnp.tag_size's default is 0.16 too, so 0.5 is passed to show it unused):
    the run is in TagSLAM's world, tag 2 where the file puts it."""
    root = realdata / "tagslam_test_16"
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "tag_detections.bag").write_bytes(
        bz2.decompress((root / "tag_detections.bag.bz2").read_bytes())
    )
    for name in ("cameras.yaml", "tagslam.yaml"):
        shutil.copy(root / name, lab / name)
    monkeypatch.chdir(tmp_path)
    assert (
        main(
            [
                "init",
                "--reference",
                "lab/tag_detections.bag",
                "--camera",
                "lab/cameras.yaml",
                "--tag-size",
                "0.5",
                "--survey",
                "lab/tagslam.yaml",
                "-o",
                "lab/pipeline.yaml",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert (
        "survey: tagslam, known tags [2]; tag sizes from it: {2: 0.16}, 0.16 m for the "
        "others (tag size 0.5 not written: the file sizes all)" in out
    )
    stages = yaml.safe_load((lab / "pipeline.yaml").read_text())["stages"]
    assert stages == {
        "pnp": {"tag_sizes_from": "tagslam.yaml"},  # no stale tag_size beside
        "edges": {"on_disconnected": "keep"},
        "optimize": {"survey": {"file": "tagslam.yaml"}},
    }
    assert main(["run", "-p", "lab/pipeline.yaml", "optimize"]) == 0
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.spec import load_pipeline
    from tagtrail.stages import REGISTRY

    runner = Runner(load_pipeline(lab / "pipeline.yaml", REGISTRY))
    assert (_artifact(runner, "pnp", "observations")["size_m"] == 0.16).all()
    report = _artifact(runner, "optimize", "report")
    assert report.survey is not None and report.survey.tags == [2]
    assert report.survey.res_pos_max_m < 1e-4
    tag2 = _artifact(runner, "optimize", "tag_map").set_index("tag_id").loc[2]
    assert [tag2.x_m, tag2.y_m, tag2.z_m] == pytest.approx([0, 0, 2.0], abs=1e-4)  # lab @ tag


def test_init_survey_field_layout_and_bad_files(
    realdata: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    """A field layout gives poses but no sizes: ``tag_size`` stays the one size; a file that
    is no known-poses file is one error line naming it."""
    photos = realdata / "photonvision_frc2024_field"
    monkeypatch.chdir(tmp_path)
    assert (
        main(
            [
                "init",
                "--reference",
                str(photos / "images"),
                "--tag-size",
                "0.1651",
                "--survey",
                str(photos / "2024-crescendo.json"),
            ]
        )
        == 0
    )
    assert (
        "tag size 0.1651 m for every tag: a WPILib/PhotonVision field layout gives no "
        "tag sizes" in capsys.readouterr().out
    )
    stages = yaml.safe_load(Path("pipeline.yaml").read_text())["stages"]
    assert stages["pnp"] == {"tag_size": 0.1651}
    assert stages["edges"] == {"on_disconnected": "keep"}
    assert (
        Path(stages["optimize"]["survey"]["file"]).resolve()
        == (photos / "2024-crescendo.json").resolve()
    )
    cameras = realdata / "tagslam_test_16" / "cameras.yaml"
    assert (
        main(["init", "--force", "--reference", str(photos / "images"), "--survey", str(cameras)])
        == 2
    )
    assert (
        one_error_line(capsys) == f"error: --survey: {cameras}: not a known-poses file "
        "(expected TagSLAM's tagslam.yaml with bodies:, a WPILib/PhotonVision field layout "
        "JSON with tags: [...], or a tagtrail tag_map.yaml)"
    )

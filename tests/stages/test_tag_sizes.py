"""Tag sizes from the known-poses files (``pnp.tag_sizes_from``) on TagSLAM's real recordings:
the sizes of ``tagslam.yaml`` (per tag and the default body's) and of a ``tag_map.yaml`` written
by tagtrail give the pnp observations the explicit sizes give; a wrong size in the file scales
the map, and a similarity to surveyed positions scales it back (``size_m`` with it); the sizes
(not the rest of the file) are in pnp's cache key; bad files are one line."""

from __future__ import annotations

import bz2
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from tagtrail.errors import SpecError
from tagtrail.io.layouts import write_tag_map
from tagtrail.runner.spec import load_pipeline
from tagtrail.stages import REGISTRY
from tests.stages.pipelines import artifact as _artifact
from tests.stages.pipelines import pipeline_file as _pipeline
from tests.stages.pipelines import run_stages as _run
from tests.tagslam import tagslam_reference as _tagslam_reference


@pytest.fixture(scope="module")
def bags(realdata: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """TagSLAM test 1's and 16's detection bags, decompressed once."""
    out = tmp_path_factory.mktemp("tagslam")
    bags = {}
    for name in ("tagslam_test_1", "tagslam_test_16"):
        bags[name] = out / f"{name}.bag"
        bags[name].write_bytes(
            bz2.decompress((realdata / name / "tag_detections.bag.bz2").read_bytes())
        )
    return bags


def _dataset(realdata: Path, bags: dict[str, Path], name: str) -> str:
    return f"{{source: {bags[name]}, camera: {realdata / name / 'cameras.yaml'}}}"


def _distances(tag_map: pd.DataFrame) -> np.ndarray:
    p = tag_map[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
    return np.linalg.norm(p[:, None] - p[None], axis=2)[np.triu_indices(len(p), 1)]


@pytest.mark.parametrize(
    ("name", "listed", "size"),
    [
        ("tagslam_test_1", {0: 0.225}, 0.225),  # perch: tag 0 listed; default body perch
        ("tagslam_test_16", {2: 0.16}, 0.16),  # lab: tag 2 listed; default body lab
    ],
)
def test_tagslam_yaml_sizes_are_the_explicit_sizes(
    realdata: Path, bags: dict[str, Path], tmp_path: Path, name: str, listed: dict, size: float
) -> None:
    """The file lists one tag; the others are the default body's (``default_tag_size``), as
    TagSLAM sizes the tags it discovers: ``tag_size`` (0.5 here) is then not used."""
    dataset = _dataset(realdata, bags, name)
    stages = {"pnp": {"tag_size": 0.5, "tag_sizes_from": str(realdata / name / "tagslam.yaml")}}
    path = _pipeline(tmp_path, dataset, stages)
    given = load_pipeline(path, REGISTRY).params_for("pnp", "reference").tag_sizes_from  # type: ignore[attr-defined]
    assert (given.format, given.sizes, given.default) == ("tagslam", listed, size)
    from_file = _artifact(_run(path, "pnp"), "pnp", "observations")
    explicit = _artifact(
        _run(_pipeline(tmp_path, dataset, {"pnp": {"tag_size": size}}), "pnp"),
        "pnp",
        "observations",
    )
    assert len(set(from_file["tag_id"]) - set(listed)) >= 3  # the default sizes most of them
    pd.testing.assert_frame_equal(from_file, explicit)


def test_a_tag_map_yaml_written_by_tagtrail_sizes_its_tags(
    realdata: Path, bags: dict[str, Path], tmp_path: Path
) -> None:
    """A ``tag_map.yaml`` (tagtrail's own, relative to the pipeline's folder) gives its tags'
    sizes; an explicit ``tag_sizes`` entry wins over the file's, ``tag_size`` sizes the tags the
    file does not list (a tag map has no default)."""
    dataset = _dataset(realdata, bags, "tagslam_test_1")
    first = _run(_pipeline(tmp_path, dataset, {"pnp": {"tag_size": 0.225}}), "optimize")
    tag_map = _artifact(first, "optimize", "tag_map")
    assert sorted(tag_map["tag_id"]) == [0, 1, 2, 3]
    write_tag_map(tmp_path / "maps", tag_map[tag_map["tag_id"] != 3], anchor_id=2)
    stages = {"pnp": {"tag_sizes_from": "maps/tag_map.yaml", "tag_sizes": {1: 0.2}}}
    from_file = _artifact(_run(_pipeline(tmp_path, dataset, stages), "pnp"), "pnp", "observations")
    sizes = {0: 0.225, 1: 0.2, 2: 0.225}  # and tag 3 at tag_size's default, 0.16
    explicit = _artifact(
        _run(_pipeline(tmp_path, dataset, {"pnp": {"tag_sizes": sizes}}), "pnp"),
        "pnp",
        "observations",
    )
    pd.testing.assert_frame_equal(from_file, explicit)
    assert from_file.groupby("tag_id")["size_m"].first().to_dict() == {**sizes, 3: 0.16}


def test_a_wrong_size_in_the_file_scales_the_map_and_a_similarity_scales_it_back(
    realdata: Path, bags: dict[str, Path], tmp_path: Path
) -> None:
    """Test 1's tags are 0.225 m; a ``tagslam.yaml`` saying 0.3 m makes every distance of the map
    4/3 as long (measured: within 1e-5). Put in the world of TagSLAM's own tag positions
    (``reference.bag``), a rigid fit shows it (residuals of 0.33 m); a similarity fits a scale
    of 0.75 and every length of the map goes with it: the tags' ``size_m`` comes back to
    0.2256 m, the positions within 1 mm of TagSLAM's (measured when written)."""
    root = realdata / "tagslam_test_1"
    dataset = _dataset(realdata, bags, "tagslam_test_1")
    text = (root / "tagslam.yaml").read_text()
    assert text.count("0.225") == 2  # perch's default_tag_size and tag 0's size
    (tmp_path / "wrong.yaml").write_text(text.replace("0.225", "0.3"))
    good = _artifact(
        _run(_pipeline(tmp_path, dataset, {"pnp": {"tag_size": 0.225}}), "optimize"),
        "optimize",
        "tag_map",
    )
    wrong_stages = {"pnp": {"tag_sizes_from": "wrong.yaml"}}
    wrong = _artifact(
        _run(_pipeline(tmp_path, dataset, wrong_stages), "optimize"), "optimize", "tag_map"
    )
    assert (wrong["size_m"] == 0.3).all()
    np.testing.assert_allclose(_distances(wrong) / _distances(good), 0.3 / 0.225, rtol=1e-4)

    ref_bag = tmp_path / "reference.bag"
    ref_bag.write_bytes(bz2.decompress((root / "reference.bag.bz2").read_bytes()))
    ref_tags, _ = _tagslam_reference(ref_bag, root)
    known = {i: {"position": [float(v) for v in T[:3, 3]]} for i, T in ref_tags.items()}
    assert sorted(known) == [0, 1, 2, 3]
    fits = {}
    for model in ("rigid", "similarity"):
        stages = {**wrong_stages, "optimize": {"survey": {"tags": known, "model": model}}}
        runner = _run(_pipeline(tmp_path, dataset, stages), "optimize")
        fits[model] = (
            _artifact(runner, "optimize", "tag_map"),
            _artifact(runner, "optimize", "report").survey,
        )
    rigid, similarity = fits["rigid"][1], fits["similarity"][1]
    assert rigid is not None and similarity is not None
    assert rigid.res_pos_max_m > 0.2
    assert similarity.scale == pytest.approx(0.225 / 0.3, rel=0.005)
    assert similarity.res_pos_max_m < 0.002
    moved = fits["similarity"][0]
    assert np.abs(moved["size_m"] - 0.225).max() < 0.001
    for col in ("size_m", "std_pos_m", "res_t_rms_m"):
        np.testing.assert_allclose(moved[col], wrong[col] * similarity.scale, rtol=1e-12)
    assert (moved["std_pos_m"] > 0).sum() == 3  # the anchor's is 0


def test_the_sizes_in_the_file_are_in_the_cache_key(
    realdata: Path, bags: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With one ``tagslam.yaml`` named (relative paths) by ``pnp.tag_sizes_from`` and
    ``optimize.survey.file``: moving a known tag reruns optimize, not pnp; changing a size
    reruns pnp."""
    lab = tmp_path / "lab"
    lab.mkdir()
    doc = yaml.safe_load((realdata / "tagslam_test_16" / "tagslam.yaml").read_text())
    (lab / "tagslam.yaml").write_text(yaml.safe_dump(doc))
    (lab / "pipeline.yaml").write_text(
        yaml.safe_dump(
            {
                "datasets": {
                    "reference": yaml.safe_load(_dataset(realdata, bags, "tagslam_test_16"))
                },
                "stages": {
                    "pnp": {"tag_sizes_from": "tagslam.yaml"},
                    "optimize": {"survey": {"file": "tagslam.yaml"}},
                },
            }
        )
    )
    monkeypatch.chdir(tmp_path)  # not the pipeline's folder

    def plan() -> dict[str, tuple[str, str]]:
        from tagtrail.runner.execute import Runner

        runner = Runner(load_pipeline(lab / "pipeline.yaml", REGISTRY))
        return {s.stage: (s.status, s.reason) for s in runner.plan(["optimize"])}

    _run(lab / "pipeline.yaml", "optimize")
    assert {s for s, _ in plan().values()} == {"cached"}
    lab_body = doc["bodies"][0]["lab"]
    lab_body["tags"][0]["pose"]["position"]["z"] = 1.1  # tag 2 moved
    (lab / "tagslam.yaml").write_text(yaml.safe_dump(doc))
    states = plan()
    assert states["pnp"][0] == "cached" and states["edges"][0] == "cached"
    assert states["optimize"] == (
        "stale",
        "params changed: survey.known.2.position: [0.0, 0.0, 2.0] → [0.0, 0.0, 2.1]",
    )
    lab_body["default_tag_size"] = lab_body["tags"][0]["size"] = 0.2
    (lab / "tagslam.yaml").write_text(yaml.safe_dump(doc))
    states = plan()
    assert states["pnp"] == (
        "stale",
        "params changed: tag_sizes_from.default: 0.16 → 0.2, tag_sizes_from.sizes.2: 0.16 → 0.2",
    )
    runner = _run(lab / "pipeline.yaml", "pnp")
    assert (_artifact(runner, "pnp", "observations")["size_m"] == 0.2).all()


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        (
            "absent.yaml",
            None,
            r"absent.yaml: tag-sizes file not found \(pnp.tag_sizes_from; a "
            r"relative path is taken from the pipeline file's folder\)",
        ),
        ("bad.yaml", "bodies: [\n", r"bad.yaml: cannot read the tag-sizes file: while parsing"),
        ("cameras.yaml", "cam0: {intrinsics: [1, 1, 1, 1]}\n", r"cameras.yaml: not a known-poses"),
        ("field.json", None, r"field.json: a WPILib/PhotonVision field layout gives no tag sizes"),
        (
            "tagslam.yaml",
            "bodies:\n - rig: {is_static: false, tags: [{id: 1}]}\n",
            r"tagslam.yaml: no tag size given \(a tagslam file sizes tags with size: or "
            r"default_tag_size:\)",
        ),
        (
            "tagslam.yaml",
            "bodies:\n - lab: {default_tag_size: -0.1}\n",
            r"tagslam.yaml: bodies.lab.default_tag_size: expected a size > 0 m, got -0.1",
        ),
        (
            "tag_map.yaml",
            "tags: {'tag36h11:1': {position: [0, 0, 0], size: 0}}\n",
            r"tag_map.yaml: tag 1: size: expected a size > 0 m, got 0",
        ),
    ],
)
def test_bad_tag_size_files_are_one_line(
    realdata: Path, tmp_path: Path, name: str, text: str | None, message: str
) -> None:
    if name == "field.json":
        text = (realdata / "photonvision_frc2024_field" / "2024-crescendo.json").read_text()
    if text is not None:
        (tmp_path / name).write_text(text)
    path = _pipeline(tmp_path, "{source: imgs}", {"pnp": {"tag_sizes_from": name}})
    with pytest.raises(SpecError, match=message) as err:
        load_pipeline(path, REGISTRY, check_sources=False)
    assert "\n" not in str(err.value) and "stages.pnp.tag_sizes_from" in str(err.value)

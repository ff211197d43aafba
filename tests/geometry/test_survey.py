"""geometry.survey: known tag poses, the fit of a map to them, and the file layouts parsed."""

from __future__ import annotations

import numpy as np
import pytest

from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import R_from_rotvec, inv, make_T, quat_xyzw_from_R
from tagtrail.geometry.survey import (
    WPILIB_R_SPEC,
    Survey,
    fit_survey,
    from_tag_map,
    from_tagslam,
    from_wpilib,
    make_survey,
    parse_survey,
    parse_tag_sizes,
)


def _scene(seed: int = 3, n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Tag ids and world_T_tag ``(n, 4, 4)`` spread over a few metres."""
    rng = np.random.default_rng(seed)
    R = R_from_rotvec(rng.normal(scale=1.0, size=(n, 3)))
    t = rng.uniform(-3, 3, size=(n, 3))
    return np.arange(10, 10 + n), make_T(R, t)


def _known(ids: np.ndarray, T: np.ndarray, pick: list[int], full: bool) -> Survey:
    k = np.searchsorted(ids, pick)
    return make_survey(
        [(int(ids[j]), T[j, :3, 3], T[j, :3, :3] if full else None, 0.16) for j in k]
    )


@pytest.mark.parametrize(
    ("pick", "full"), [([12], True), ([10, 13, 16], False), ([11, 14, 15, 17], True)]
)
def test_a_moved_map_is_put_back_in_the_surveyed_world(pick: list[int], full: bool) -> None:
    ids, world_T_tag = _scene()
    map_T_world = make_T(R_from_rotvec([0.3, -1.2, 0.7]), [4.0, -2.0, 1.0])
    map_T_tag = map_T_world @ world_T_tag
    fit = fit_survey(ids, map_T_tag, _known(ids, world_T_tag, pick, full))
    back = fit.apply(map_T_tag)
    assert np.abs(back - world_T_tag).max() < 1e-9
    assert fit.scale == 1.0 and fit.ids.tolist() == pick and fit.missing == []
    assert fit.res_pos_m.max() < 1e-9
    assert (fit.res_rot_deg.max() < 1e-6) if full else np.isnan(fit.res_rot_deg).all()


def test_similarity_recovers_the_scale_and_rigid_reports_it_as_residual() -> None:
    ids, world_T_tag = _scene()
    map_T_tag = world_T_tag.copy()
    map_T_tag[:, :3, 3] *= 0.95  # a map 5 % small (a wrong tag size)
    known = _known(ids, world_T_tag, [10, 12, 15, 17], True)
    sim = fit_survey(ids, map_T_tag, known, similarity=True)
    assert sim.scale == pytest.approx(1 / 0.95, rel=1e-3)
    assert sim.res_pos_m.max() < 0.01  # what is left: the corners (tag sizes) were not scaled
    rigid = fit_survey(ids, map_T_tag, known)
    assert rigid.scale == 1.0 and rigid.res_pos_m.max() > 0.05


def test_residuals_at_the_known_tags_measure_their_disagreement() -> None:
    ids, world_T_tag = _scene()
    known = _known(ids, world_T_tag, ids.tolist(), False)
    map_T_tag = world_T_tag.copy()
    map_T_tag[np.searchsorted(ids, 15), :3, 3] += [0.0, 0.0, 0.04]  # one surveyed tag 4 cm off
    fit = fit_survey(ids, map_T_tag, known)
    worst = int(fit.ids[np.argmax(fit.res_pos_m)])
    assert worst == 15 and 0.02 < fit.res_pos_m.max() < 0.04  # least squares spreads some
    assert np.delete(fit.res_pos_m, np.searchsorted(fit.ids, 15)).max() < 0.015


def test_degenerate_surveys_say_what_is_missing() -> None:
    ids, T = _scene()
    with pytest.raises(ValueError, match=r"none of the known tags \[99\] is in the map"):
        fit_survey(ids, T, make_survey([(99, [0, 0, 0], None, None)]))
    with pytest.raises(ValueError, match=r"position-only known tags \[10, 11\] do not fix"):
        fit_survey(ids, T, _known(ids, T, [10, 11], False))
    line = T.copy()
    line[:3, :3, 3] = [[0, 0, 0], [1, 0, 0], [2, 0, 0]]
    with pytest.raises(ValueError, match="do not fix the world"):
        fit_survey(ids, line, _known(ids, line, [10, 11, 12], False))
    with pytest.raises(ValueError, match="a similarity needs 3 or more known tags"):
        fit_survey(ids, T, _known(ids, T, [12], True), similarity=True)
    fit = fit_survey(
        ids, T, make_survey([(12, T[2, :3, 3], T[2, :3, :3], None), (99, [0, 0, 0], None, None)])
    )
    assert fit.missing == [99]
    with pytest.raises(ValueError, match="tag 3 is given twice"):
        make_survey([(3, [0, 0, 0], None, None), (3, [1, 0, 0], None, None)])


def test_tagslam_known_poses_compose_body_and_tag() -> None:
    """TagSLAM tag poses are in their body's frame; rotations are rotation vectors; only static
    bodies with a pose count; sizes from the tag or the body's default_tag_size."""
    doc = {
        "bodies": [
            {
                "lab": {
                    "is_static": True,
                    "default_tag_size": 0.2,
                    "pose": {
                        "position": {"x": 1, "y": 0, "z": 1},
                        "rotation": {"x": 0, "y": 0, "z": np.pi / 2},
                    },
                    "tags": [
                        {
                            "id": 2,
                            "size": 0.16,
                            "pose": {
                                "position": {"x": 1, "y": 0, "z": 0},
                                "rotation": {"x": 0.3, "y": 0, "z": 0},
                            },
                        },
                        {
                            "id": 5,
                            "pose": {
                                "position": {"x": 0, "y": 0, "z": 0},
                                "rotation": {"x": 0, "y": 0, "z": 0},
                            },
                        },
                        {"id": 6},
                    ],
                }
            },
            {"rig": {"is_static": False, "type": "simple"}},
        ]
    }
    sv = from_tagslam(doc)
    assert sv.ids.tolist() == [2, 5] and sv.size.tolist() == [0.16, 0.2]
    assert np.allclose(sv.position, [[1, 1, 1], [1, 0, 1]])
    expect = R_from_rotvec([0, 0, np.pi / 2]) @ R_from_rotvec([0.3, 0, 0])
    assert np.allclose(sv.R[0], expect)
    with pytest.raises(ValueError, match="no tag with a pose"):
        from_tagslam({"bodies": [{"rig": {"is_static": False}}]})


def test_tagslam_sizes_of_every_body_and_the_default_bodys_default() -> None:
    """Sizes of tags with or without a pose, on static bodies or not (a rig's tags are seen too);
    the default is the ``default_body``'s ``default_tag_size`` only (another body's sizes its
    own tags); an id twice is refused."""
    doc = {
        "default_body": "lab",
        "bodies": [
            {
                "lab": {
                    "is_static": True,
                    "default_tag_size": 0.2,
                    "tags": [{"id": 2, "size": 0.16}, {"id": 6}],
                }
            },
            {"rig": {"is_static": False, "default_tag_size": 0.05, "tags": [{"id": 9}]}},
            {"cart": {"is_static": False, "tags": [{"id": 11, "size": 0.3}, {"id": 12}]}},
        ],
    }
    fmt, sizes = parse_tag_sizes(doc)
    assert fmt == "tagslam" and sizes.default == 0.2
    assert sizes.per_id == {2: 0.16, 6: 0.2, 9: 0.05, 11: 0.3}  # 12: the default's
    sizes = parse_tag_sizes({**doc, "default_body": "rig"})[1]
    assert sizes.default == 0.05
    assert parse_tag_sizes({"bodies": doc["bodies"]})[1].default is None
    doc["bodies"][1]["rig"]["tags"].append({"id": 2})
    with pytest.raises(ValueError, match="tag 2 is given twice"):
        parse_tag_sizes(doc)


def test_wpilib_layout_tag_frame_is_turned_to_spec() -> None:
    """WPILib: the tag's +X points out of its face, Z up. A tag facing the field's -X (yaw
    180 deg) has SPEC z (out of the face) along -X, y (up) along +Z, x (right) along -Y."""
    q_wxyz = (0.0, 0.0, 0.0, 1.0)  # W, X, Y, Z: yaw 180 deg
    doc = {
        "tags": [
            {
                "ID": 7,
                "pose": {
                    "translation": {"x": 16.5, "y": 5.5, "z": 1.45},
                    "rotation": {"quaternion": dict(zip("WXYZ", q_wxyz, strict=True))},
                },
            }
        ],
        "field": {"length": 16.54, "width": 8.21},
    }
    sv = from_wpilib(doc)
    R = sv.R[0]
    assert np.allclose(R[:, 2], [-1, 0, 0]) and np.allclose(R[:, 1], [0, 0, 1])
    assert np.allclose(R[:, 0], [0, -1, 0]) and np.isclose(np.linalg.det(WPILIB_R_SPEC), 1)
    assert parse_survey(doc)[0] == "wpilib"
    with pytest.raises(ValueError, match=r"tags\[0\]: expected \{ID, pose"):
        from_wpilib({"tags": [{"ID": 1}]})


def test_tag_map_layout_and_inline_form() -> None:
    R = R_from_rotvec([0.1, 0.2, 0.3])
    q = quat_xyzw_from_R(R)
    doc = {
        "world_frame": "map",
        "anchor_tag": "tag36h11:3",
        "tags": {
            "tag36h11:3": {
                "position": {"x": 0, "y": 0, "z": 0},
                "orientation": dict(zip("xyzw", q.tolist(), strict=True)),
                "size": 0.1,
            },
            "tag36h11:8": {"position": {"x": 1, "y": 2, "z": 3}},
        },
    }
    fmt, sv = parse_survey(doc)
    assert fmt == "tag_map" and sv.ids.tolist() == [3, 8] and sv.full.tolist() == [True, False]
    assert geodesic_angle(sv.R[0], R) < 1e-9 and sv.size[0] == 0.1
    inline = from_tag_map({4: {"position": [1, 2, 3], "orientation": [0, 0, 0, 1]}})
    assert inline.ids.tolist() == [4] and np.allclose(inline.R[0], np.eye(3))
    with pytest.raises(ValueError, match="not a known-poses file"):
        parse_survey({"camera": {}})
    with pytest.raises(ValueError, match=r"tag 'tagX': expected tag36h11:<id>"):
        from_tag_map({"tags": {"tagX": {"position": [0, 0, 0]}}})
    with pytest.raises(ValueError, match="the quaternion has no length"):
        from_tag_map({1: {"position": [0, 0, 0], "orientation": [0, 0, 0, 0]}})


def test_apply_moves_poses_not_their_shape() -> None:
    ids, T = _scene()
    fit = fit_survey(ids, T, _known(ids, inv(T[:1]) @ T, [10], True))
    moved = fit.apply(T)
    assert np.allclose(moved[0], np.eye(4))
    rel = inv(moved[0]) @ moved[1]
    assert np.allclose(rel, inv(T[0]) @ T[1])

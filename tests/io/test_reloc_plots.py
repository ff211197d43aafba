"""The relocalization pictures (issue 30): what each draws, read from the matplotlib objects, and
``map.png`` following ``report.plane`` (a change redraws it, with nothing else to run)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.lines import Line2D
from matplotlib.quiver import Quiver

from tagtrail.cli import main
from tagtrail.io import reloc_files
from tagtrail.io.reloc_plots import is_photo_set, map_figure, point_figure
from tagtrail.schemas.artifacts import columns
from tagtrail.sim import simulate


def legend(fig) -> list[str]:
    leg = fig.axes[0].get_legend()
    return [] if leg is None else [t.get_text() for t in leg.get_texts()]


def drawn_lines(fig) -> list[Line2D]:
    """Lines with a visible stroke (``linestyle`` not None) and at least 2 points."""
    return [
        ln
        for ln in fig.axes[0].get_lines()
        if ln.get_linestyle() not in ("None", "") and len(ln.get_xdata()) >= 2
    ]


EMPTY = pd.DataFrame({c: np.zeros(0) for c in columns("report.relocalization")})
LOOP = np.column_stack([np.cos(np.linspace(0, 6, 300)), np.sin(np.linspace(0, 6, 300))])
# 15 photos scattered over a 16 x 8 m field, in file-name order (not a path)
PHOTOS = np.random.default_rng(4).uniform([0, 0], [16, 8], (15, 2))


def test_photo_sets_and_paths_are_told_apart() -> None:
    assert not is_photo_set(LOOP)
    assert is_photo_set(PHOTOS)
    # a robot at 0.3 m/s recorded at 10 Hz around a 3 m circle: a path
    a = np.arange(0, 2 * np.pi, 0.03 / 1.5)
    assert not is_photo_set(np.column_stack([1.5 * np.cos(a), 1.5 * np.sin(a)]))
    # hand-held photos walking around a 4.7 m room, 0.8 m apart: photos
    b = np.arange(0, 4 * np.pi, 0.8 / 2.35)
    assert is_photo_set(np.column_stack([2.35 * np.cos(b), 2.35 * np.sin(b)]))


def test_recording_map_lists_only_what_is_drawn() -> None:
    fig = map_figure(LOOP, np.zeros((0, 2)), EMPTY, LOOP[::50], [1, 2, 3, 4, 5, 6])
    assert legend(fig) == ["reference path", "start", "end", "tags"]  # no "query poses"
    fig = map_figure(LOOP, np.zeros((0, 2)), EMPTY)  # no tags either
    assert legend(fig) == ["reference path", "start", "end"]


def test_photo_set_is_drawn_as_separate_camera_views() -> None:
    heading = np.linspace(-1, 1, len(PHOTOS))
    fig = map_figure(
        PHOTOS, np.zeros((0, 2)), EMPTY, PHOTOS[:3] + 0.5, [7, 8, 9], ref_heading_rad=heading
    )
    assert legend(fig) == ["camera views (15 photos; #: file order)", "tags"]
    assert drawn_lines(fig) == []  # no line joins the photos
    (quiver,) = [c for c in fig.axes[0].collections if isinstance(c, Quiver)]
    assert len(quiver.get_offsets()) == len(PHOTOS)  # a viewing direction per photo
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert [f"#{i}" for i in range(1, 16)] == texts[:15]


def _point_row(q: np.ndarray, k: int, ref: np.ndarray, hq_deg: float) -> pd.Series:
    a, b = ref[k], ref[k + 1]
    t = float(np.clip((q - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1))
    p = a + t * (b - a)
    href = math.degrees(math.atan2(*(b - a)[::-1]))
    (du, dv), (qu, qv) = b - a, q - p
    side = float(np.sign(du * qv - dv * qu))
    d = float(np.linalg.norm(q - p))
    return pd.Series(
        {
            "nearest_ref_idx": k,
            "distance_m": d,
            "heading_error_deg": hq_deg - href,
            "query_heading_deg": hq_deg,
            "ref_heading_deg": href,
            "query_u": q[0],
            "query_v": q[1],
            "ref_u": p[0],
            "ref_v": p[1],
            "cross_track_m": side * d,
        }
    )


def test_point_mode_is_a_close_up_from_above() -> None:
    ref = np.column_stack([np.linspace(0, 4, 41), 0.05 * np.linspace(0, 4, 41) ** 2])
    rng = np.random.default_rng(1)
    samples = np.array([1.5, 0.6]) + rng.normal(0, 0.004, (40, 2))
    q = np.median(samples, axis=0)
    row = _point_row(q, 15, ref, 20.0)
    fig = point_figure(row, ref, samples, np.radians(20.0 + rng.normal(0, 0.3, 40)))
    names = legend(fig)
    for want in (
        "reference path",
        "nearest segment (samples 15, 16)",
        "query samples (n=40)",
        "parked pose (median position)",
        "nearest point of the reference",
    ):
        assert want in names, names
    assert any(n.startswith(f"D = {row['distance_m']:.4f} m") for n in names)
    assert any(n.startswith("spread: p95 radius ") for n in names)
    assert any(n.startswith("query heading") for n in names)
    assert any(n.startswith("segment heading") for n in names)
    # a close-up: the view is about the pose and its nearest point, not the whole path, and
    # not a time axis
    ax = fig.axes[0]
    x0, x1 = ax.get_xlim()
    assert x0 <= min(q[0], row["ref_u"]) and x1 >= max(q[0], row["ref_u"]) and x1 - x0 < 2.5
    assert "time" not in ax.get_xlabel()
    assert len(fig.axes) == 1


def test_map_follows_report_plane_and_a_change_redraws_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``-S report.plane=xy`` runs no stage (no query to report on) but redraws ``map.png`` in
    that plane; back to the file's plane, the first picture again, byte for byte."""
    simulate("observations", tmp_path / "data", frames=40)
    (tmp_path / "pipeline.yaml").write_text(
        "datasets:\n  reference:\n    source: data/observations\n"
    )
    pipeline = str(tmp_path / "pipeline.yaml")
    png = tmp_path / "outputs" / "reference" / "map.png"
    assert main(["run", "-p", pipeline]) == 0
    first = png.read_bytes()
    capsys.readouterr()
    drawn: list[tuple[str, str]] = []
    real = reloc_files.map_figure

    def spy(*args, **kwargs):
        drawn.append(args[5])  # axis_names
        return real(*args, **kwargs)

    monkeypatch.setattr(reloc_files, "map_figure", spy)
    assert main(["run", "-p", pipeline, "-S", "report.plane=xy"]) == 0
    assert "0 ran" in capsys.readouterr().out
    assert drawn == [("x", "y")]
    xy = png.read_bytes()
    assert xy != first
    assert main(["run", "-p", pipeline, "-S", "report.plane=xz"]) == 0
    assert png.read_bytes() not in (first, xy)
    assert main(["run", "-p", pipeline]) == 0
    assert png.read_bytes() == first

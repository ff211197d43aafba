"""Artifact schemas: tables are conformed (types cast, extras kept) or rejected by name."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pytest

from tagtrail.schemas.artifacts import SCHEMAS, conform


def test_conform_casts_and_keeps_extra_columns() -> None:
    df = pd.DataFrame(
        {
            "n_det": [1, 2],
            "frame_idx": np.array([0, 1], np.int64),
            "t_ns": [5, 6],
            "note": ["a", "b"],
            "timed": True,
        }
    )
    t = conform("extract.frames", df)
    assert t.schema.names == ["t_ns", "frame_idx", "n_det", "timed", "note"]
    assert t.schema.field("frame_idx").type == pa.int32()


def test_missing_columns_and_bad_types_are_named() -> None:
    with pytest.raises(TypeError, match=r"extract.frames lacks columns \['n_det'\]"):
        conform("extract.frames", pd.DataFrame({"t_ns": [1], "frame_idx": [0], "timed": True}))
    bad = pd.DataFrame({"t_ns": [1], "frame_idx": [2**40], "n_det": [1], "timed": True})
    with pytest.raises(TypeError, match="does not fit its schema"):
        conform("extract.frames", bad)


def test_schema_column_names_are_unique() -> None:
    for name, schema in SCHEMAS.items():
        assert len(set(schema.names)) == len(schema.names), name


def test_documents_read_like_their_json() -> None:
    from tagtrail.schemas.documents import AlignmentBlock

    al = AlignmentBlock(
        model="none",
        scale=1.0,
        rotation_deg=0.0,
        translation=[0.0, 0.0],
        inliers=0,
        common_tags=3,
        rms_m=None,
    )
    assert "scale" in al and "nope" not in al
    assert al["common_tags"] == 3 and al.get("nope", 7) == 7

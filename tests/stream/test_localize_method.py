"""The live node cannot hold frames together in time: a pipeline asking for ``joint`` is told
so, in one warning line, and posed by ``auto`` (tagtrail.stream.localize)."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import pytest

from tagtrail.schemas.artifacts import POSE_COLS
from tagtrail.stages import trajectory
from tagtrail.stream.localize import Localizer, Params

TAG_MAP = pd.DataFrame(
    {
        "tag_id": [0],
        **{c: [v] for c, v in zip(POSE_COLS, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), strict=True)},
        "size_m": [0.16],
    }
)


@pytest.mark.parametrize(
    ("method", "used", "warned"),
    [("joint", "auto", True), ("auto", "auto", False), ("pnp", "pnp", False)],
)
def test_joint_is_posed_by_auto_and_the_node_says_so(
    caplog: pytest.LogCaptureFixture, method: str, used: str, warned: bool
) -> None:
    params = Params(trajectory=trajectory.Params(method=method))  # type: ignore[arg-type]
    with caplog.at_level(logging.WARNING, logger="tagtrail.stream"):
        loc = Localizer(TAG_MAP, params)
    assert loc.method == used
    said = [
        r.getMessage() for r in caplog.records if "trajectory.method is joint" in r.getMessage()
    ]
    assert len(said) == int(warned)
    assert np.isfinite(loc.world_T_tag).all()

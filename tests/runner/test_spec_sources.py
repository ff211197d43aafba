"""A pipeline can be read for its parameters on a machine without its recordings."""

from __future__ import annotations

from pathlib import Path

import pytest

from tagtrail.errors import SpecError
from tagtrail.runner.spec import load_pipeline
from tagtrail.stages import REGISTRY


def test_parameters_without_the_sources(tmp_path: Path) -> None:
    f = tmp_path / "pipeline.yaml"
    f.write_text(
        "datasets:\n  reference: {source: bags/run1, camera: cam.yaml}\n"
        "stages:\n  pnp: {tag_size: 0.1}\n  report: {plane: xy}\n"
    )
    with pytest.raises(SpecError, match="does not exist"):
        load_pipeline(f, REGISTRY)
    pipe = load_pipeline(f, REGISTRY, check_sources=False)
    assert pipe.params_for("pnp", "reference").tag_size == 0.1  # type: ignore[attr-defined]
    assert pipe.datasets["reference"].source == (tmp_path / "bags" / "run1").resolve()

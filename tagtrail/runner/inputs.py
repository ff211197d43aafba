"""The special inputs the runner resolves for a stage: ``source`` (the dataset's recording,
opened, with a progress bar the runner owns), ``ground_truth`` (read from its folder) and
``dataset`` (the validated ``DatasetConfig`` itself, for stages that read their own data)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any

from tqdm import tqdm

from tagtrail.io.layouts import read_tag_map, read_trajectory
from tagtrail.io.sources import open_source
from tagtrail.schemas.inputs import Frame, GroundTruth, Source
from tagtrail.schemas.pipeline import DatasetConfig


class _Progress:
    """A source whose frames advance a progress bar as they are read (stages stay unaware)."""

    def __init__(self, src: Source, bar: Any) -> None:
        self._src = src
        self._bar = bar

    def __getattr__(self, name: str) -> Any:
        return getattr(self._src, name)

    def __len__(self) -> int:
        return len(self._src)

    def iter_raw(self) -> Iterator[Frame]:
        for frame in self._src.iter_raw():
            yield frame
            self._bar.update(1)

    def chunks(self, size: int) -> Iterator[list[Frame]]:
        for chunk in self._src.chunks(size):
            yield chunk
            self._bar.update(len(chunk))


def resolve(special: str, ds: DatasetConfig, label: str, stack: ExitStack) -> Any:
    """The value of special input ``special`` for dataset ``ds``; what it opens is closed by
    ``stack``. ``label`` names the node on the progress bar."""
    if special == "dataset":
        return ds
    if special == "ground_truth":
        assert ds.ground_truth is not None
        tags, anchor = read_tag_map(ds.ground_truth)
        return GroundTruth(ds.ground_truth, read_trajectory(ds.ground_truth), tags, anchor)
    src = stack.enter_context(open_source(ds))
    bar = stack.enter_context(tqdm(total=len(src), unit="frame", desc=label, disable=None,
                                   leave=False))
    return _Progress(src, bar)

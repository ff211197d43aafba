"""The special inputs the runner resolves for a stage: ``source`` (the dataset's recording,
opened, with a progress bar the runner owns), ``ground_truth`` (read from its folder) and
``dataset`` (the validated ``DatasetConfig`` itself, for stages that read their own data).

What a stage sees of ``source`` and ``ground_truth`` depends on the code that reads them as
much as on the files: :func:`reader_closure` gives that code's fingerprint (the readers' modules
and everything they import within tagtrail, as for a stage), which enters the cache key of the
stages that take the input; ``dataset`` has no reader here (its stage reads the files itself).
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any

from tqdm import tqdm

from tagtrail.io.layouts import read_tag_map, read_trajectory
from tagtrail.io.sources import open_source
from tagtrail.runner.stage import code_closure
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


READERS = {"source": "tagtrail.io.sources", "ground_truth": "tagtrail.io.layouts"}
"""special input → the module whose code reads it (``open_source``; ``read_trajectory`` and
``read_tag_map``)."""


@functools.cache
def reader_closure(special: str) -> dict[str, str]:
    """The AST hash of every module that reads ``special`` (:data:`READERS`: the module and its
    first-party imports, docstrings and comments left out), by module name; empty for an input
    without a reader. Computed once per process, like a stage's closure."""
    name = READERS.get(special)
    if name is None:
        return {}
    closure = code_closure(importlib.import_module(name))
    return {name if m == "." else m: digest for m, digest in closure.items()}


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
    bar = stack.enter_context(
        tqdm(total=len(src), unit="frame", desc=label, disable=None, leave=False)
    )
    return _Progress(src, bar)

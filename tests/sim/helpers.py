"""Helpers of the simulator tests: a process-lifetime detector, bag reading."""

from __future__ import annotations

import ctypes
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader

from tagtrail.io.msgs import typestore

SMALL = {"frames": 48, "query_frames": 4, "seed": 3}


@lru_cache(maxsize=4)
def detector(quad_decimate: float = 1.0) -> Any:
    """A pupil-apriltags detector kept alive for the whole process.

    pupil-apriltags 1.0.4.post11 can segfault in ``Detector.__del__`` at interpreter exit
    (NOTES): an extra reference that is never released keeps ``__del__`` from ever running.
    """
    from pupil_apriltags import Detector

    det = Detector(families="tag36h11", quad_decimate=quad_decimate)
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(det))
    return det


def read_topic(bag: Path, topic: str) -> list[tuple[int, Any]]:
    """``(log time ns, message)`` of every message on ``topic``, read with rosbags."""
    with AnyReader([Path(bag)], default_typestore=typestore()) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:  # messages(connections=[]) would mean "all topics"
            return []
        return [
            (t, reader.deserialize(raw, c.msgtype))
            for c, t, raw in reader.messages(connections=conns)
        ]


def image_of(msg: Any) -> np.ndarray:
    return np.asarray(msg.data, dtype=np.uint8).reshape(msg.height, msg.width, 3)

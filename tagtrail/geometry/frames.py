"""A tree of named frames (ROS tf): the transform between two frames through a chain of edges.

Edges are ``(parent, child, parent_T_child)``; a chain may run up and down the tree, e.g.
``base_link → camera_link → camera_color_optical_frame`` or through a common parent
(``base_T_cam = inv(root_T_base) @ root_T_cam``). Frame names compare without a leading ``/``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

import numpy as np

from tagtrail.geometry.arrays import F64
from tagtrail.geometry.se3 import inv


def _name(frame: str) -> str:
    return frame.lstrip("/")


def chain(edges: Iterable[tuple[str, str, F64]], source: str, target: str) -> F64 | None:
    """``source_T_target`` (4, 4) composed along the edges (breadth first: the shortest
    chain); the identity when the frames are the same, None when no chain links them (or an
    edge on it is not a finite transform)."""
    source, target = _name(source), _name(target)
    if source == target:
        return np.eye(4)
    links: dict[str, list[tuple[str, F64]]] = {}
    for parent, child, T in edges:
        p, c = _name(parent), _name(child)
        T = np.asarray(T, dtype=np.float64)
        links.setdefault(p, []).append((c, T))
        links.setdefault(c, []).append((p, inv(T)))
    seen = {source: np.eye(4)}
    todo = deque([source])
    while todo:
        frame = todo.popleft()
        for nxt, T in links.get(frame, []):
            if nxt in seen:
                continue
            seen[nxt] = seen[frame] @ T
            if nxt == target:
                out: F64 = seen[nxt]
                return out if np.isfinite(out).all() else None
            todo.append(nxt)
    return None

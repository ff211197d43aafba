"""Camera calibration files → :class:`~tagtrail.geometry.camera.CameraModel`.

A ROS camera_info YAML (``camera_calibration`` output), or the short form ``camera: {width,
height, fx, fy, cx, cy, distortion_model, distortion}``; every problem is one
:class:`SourceError` line naming the file and the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from tagtrail.errors import SourceError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.camera import CameraModel
from tagtrail.io.layouts import load_yaml

_ROS_KEYS = ("image_width", "image_height", "camera_matrix", "distortion_model",
             "distortion_coefficients")  # fmt: skip
_ROS_NEEDS = ("a camera_info YAML needs image_width, image_height, camera_matrix.data (9 numbers), "
              "distortion_model and distortion_coefficients.data")  # fmt: skip


def read_camera_file(path: Path | str) -> CameraModel:
    """From a ROS camera_info YAML (``camera_calibration`` output).

    Also accepts the simpler form ``camera: {width, height, fx, fy, cx, cy,
    distortion_model, distortion}`` (the realdata ``meta.yaml`` files), with or without the
    ``camera:`` level. Every problem is one :class:`SourceError` line naming the file.
    """
    path = Path(path)
    doc = load_yaml(path, "camera file")
    try:
        return _from_doc(doc)
    except SourceError as err:
        raise SourceError(f"{path}: {err}") from err

def _from_doc(doc: Any) -> CameraModel:
    if doc is None:
        raise SourceError(f"empty file; {_ROS_NEEDS}")
    if not isinstance(doc, dict):
        raise SourceError(f"not a camera_info YAML (it holds {type(doc).__name__}, not a "
                          f"mapping); {_ROS_NEEDS}")  # fmt: skip
    cam = doc["camera"] if isinstance(doc.get("camera"), dict) else doc
    if "fx" in cam and not any(k in doc for k in _ROS_KEYS):
        return _from_simple(cam)
    missing = [k for k in _ROS_KEYS[:3] if k not in doc]
    if missing:
        raise SourceError(f"not a camera_info YAML: no {', '.join(missing)}; {_ROS_NEEDS}")
    K, dist = doc["camera_matrix"], doc.get("distortion_coefficients") or {}
    if not isinstance(K, dict) or "data" not in K:
        raise SourceError("camera_matrix needs a 'data:' list of 9 numbers (K, row-major)")
    if not isinstance(dist, dict):
        raise SourceError("distortion_coefficients needs a 'data:' list of numbers")
    return CameraModel(
        width=_pixels(doc["image_width"], "image_width"),
        height=_pixels(doc["image_height"], "image_height"),
        K=_numbers(K["data"], "camera_matrix.data", 9),
        D=_numbers(dist.get("data") or [], "distortion_coefficients.data"),
        distortion_model=str(doc.get("distortion_model", "plumb_bob")),
    )

def _from_simple(cam: dict[str, Any]) -> CameraModel:
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in cam]
    if missing:
        raise SourceError(f"camera: no {', '.join(missing)} (the short form needs width, "
                          "height, fx, fy, cx, cy and optionally distortion_model, "
                          "distortion)")  # fmt: skip
    f = {k: _number(cam[k], k) for k in ("fx", "fy", "cx", "cy")}
    D = cam.get("distortion") or cam.get("D") or []
    return CameraModel(
        width=_pixels(cam["width"], "width"),
        height=_pixels(cam["height"], "height"),
        K=np.array([f["fx"], 0.0, f["cx"], 0.0, f["fy"], f["cy"], 0.0, 0.0, 1.0]),
        D=_numbers(D, "distortion"),
        distortion_model=str(cam.get("distortion_model", "plumb_bob" if D else "none")),
    )



def _number(value: Any, name: str) -> float:
    """A YAML number (a numeric string too), else an error naming the key."""
    try:
        x = float(value) if not isinstance(value, bool) else np.nan
    except (TypeError, ValueError):
        x = np.nan
    if np.isnan(x):
        raise SourceError(f"{name} is {value!r}, not a number")
    return x


def _numbers(value: Any, name: str, n: int | None = None) -> F64:
    """A YAML list of numbers; ``n``: the length it must have."""
    if not isinstance(value, list | tuple):
        raise SourceError(f"{name} is {value!r}, not a list of numbers")
    if n is not None and len(value) != n:
        raise SourceError(f"{name} has {len(value)} numbers, needs {n}")
    return np.array([_number(v, f"{name}[{i}]") for i, v in enumerate(value)], dtype=np.float64)


def _pixels(value: Any, name: str) -> int:
    """An image size in pixels: a positive integer."""
    ok = isinstance(value, int | float | str) and not isinstance(value, bool)
    try:
        x = float(value) if ok else np.nan
    except ValueError:
        x = np.nan
    if not (np.isfinite(x) and x >= 1 and x == int(x)):
        raise SourceError(f"{name} is {value!r}, not a positive integer (pixels)")
    return int(x)

"""Camera calibration files → :class:`~tagtrail.geometry.camera.CameraModel`, recognised by content.

- a ROS camera_info YAML (``camera_calibration`` output);
- a Kalibr camchain / TagSLAM ``cameras.yaml``: ``camN: {camera_model: pinhole, intrinsics: [fx,
  fy, cx, cy], distortion_model: radtan|equidistant|none, distortion_coeffs, resolution: [w, h]}``
  (radtan = OpenCV's k1 k2 p1 p2 [k3], plumb_bob; equidistant = the fisheye model); the only
  camera, or the one named ``FILE#camN``;
- an OpenCV FileStorage YAML (``%YAML:1.0``, ``!!opencv-matrix``) or JSON as ``calibrateCamera``
  tools write: ``camera_matrix``, ``distortion_coefficients``, ``image_width``/``image_height``
  (also ``cameraMatrix``/``distCoeffs``/``image_size``);
- a PhotonVision calibration JSON (``resolution``, ``cameraIntrinsics``, the distortion under
  ``distCoeffs`` or, in older files, the misnamed ``cameraExtrinsics``);
- the short form ``camera: {width, height, fx, fy, cx, cy, distortion_model, distortion}``.

Every problem is one :class:`SourceError` line naming the file and the key.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from tagtrail.errors import SourceError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.camera import CameraModel
from tagtrail.io.layouts import load_yaml, yaml_error_text
from tagtrail.schemas.ranges import check_expansion

_ROS_KEYS = (
    "image_width",
    "image_height",
    "camera_matrix",
    "distortion_model",
    "distortion_coefficients",
)
_ROS_NEEDS = (
    "a camera_info YAML needs image_width, image_height, camera_matrix.data (9 numbers), "
    "distortion_model and distortion_coefficients.data"
)


def split_camera_path(path: Path | str) -> tuple[Path, str | None]:
    """``(file, camera name or None)`` of ``FILE`` or ``FILE#NAME`` (a camchain's camera)."""
    text = str(path)
    if not Path(text).exists() and "#" in text:
        text, name = text.rsplit("#", 1)
        return Path(text), name
    return Path(text), None


def read_camera_file(path: Path | str) -> CameraModel:
    """From a ROS camera_info YAML (``camera_calibration`` output).

    Also accepts the simpler form ``camera: {width, height, fx, fy, cx, cy,
    distortion_model, distortion}`` (the realdata ``meta.yaml`` files), with or without the
    ``camera:`` level. Every problem is one :class:`SourceError` line naming the file.
    """
    path, name = split_camera_path(path)
    doc = _load(path)
    try:
        if _is_kalibr(doc):
            return _from_kalibr(doc, name)
        if name is not None:
            raise SourceError(f"names camera {name!r} but is not a Kalibr/TagSLAM camchain")
        ros = (
            isinstance(doc, dict)
            and "camera_matrix" in doc
            and "image_width" in doc
            and ("distortion_model" in doc or "camera_name" in doc)
        )
        if isinstance(doc, dict) and any(k in doc for k in _CV_MATRIX) and not ros:
            return _from_opencv(doc)
        return _from_doc(doc)
    except SourceError as err:
        raise SourceError(f"{path}: {err}") from err


_CV_MATRIX = ("camera_matrix", "cameraMatrix", "Camera_Matrix", "cameraIntrinsics")
_CV_DIST = (
    "distortion_coefficients",
    "distCoeffs",
    "dist_coeffs",
    "Distortion_Coefficients",
    "cameraExtrinsics",
)  # PhotonVision's older files store the distortion under that name


def _load(path: Path) -> Any:
    """YAML (ROS, Kalibr), OpenCV FileStorage YAML (``%YAML:1.0``) or JSON."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return load_yaml(path, "camera file")  # its one-line error
    if path.suffix.lower() == ".json":
        try:
            return json.loads(text)
        except ValueError as err:
            raise SourceError(f"{path}: not valid JSON (camera file): {err}") from err
    if not text.lstrip().startswith("%YAML:1.0"):
        return load_yaml(path, "camera file")
    body = text.lstrip().split("\n", 1)[1] if "\n" in text.lstrip() else ""
    try:
        doc = yaml.load(body, Loader=_OpenCVLoader)  # a SafeLoader plus !!opencv-matrix
        return check_expansion(doc)
    except yaml.YAMLError as err:
        raise SourceError(
            f"{path}: not valid OpenCV YAML (camera file): {yaml_error_text(err)}"
        ) from err
    except (ValueError, RecursionError) as err:
        raise SourceError(f"{path}: refused (camera file): {err or 'nested too deeply'}") from err


class _OpenCVLoader(yaml.SafeLoader):
    """PyYAML's safe loader reading OpenCV's ``!!opencv-matrix`` as a mapping."""


_OpenCVLoader.add_constructor(
    "tag:yaml.org,2002:opencv-matrix",
    lambda loader, node: loader.construct_mapping(node, deep=True),  # type: ignore[arg-type]
)


def _is_kalibr(doc: Any) -> bool:
    return (
        isinstance(doc, dict)
        and bool(doc)
        and all(isinstance(v, dict) and "intrinsics" in v for v in doc.values())
    )


def _from_kalibr(doc: dict[str, Any], name: str | None) -> CameraModel:
    if name is None and len(doc) > 1:
        raise SourceError(
            f"a camchain of {len(doc)} cameras ({', '.join(map(str, doc))}): name one as FILE#NAME"
        )
    if name is not None and name not in doc:
        raise SourceError(f"no camera {name!r} (it has {', '.join(map(str, doc))})")
    key = name if name is not None else next(iter(doc))
    cam = doc[key]
    model = str(cam.get("camera_model", "pinhole"))
    if model != "pinhole":
        raise SourceError(f"{key}: camera_model {model!r} is not supported (pinhole only)")
    fx, fy, cx, cy = _numbers(cam["intrinsics"], f"{key}.intrinsics", 4)
    res = cam.get("resolution")
    if not isinstance(res, list | tuple) or len(res) != 2:
        raise SourceError(f"{key}: resolution is {res!r}, not [width, height]")
    dist = str(cam.get("distortion_model", "none"))
    models = {"radtan": "plumb_bob", "equidistant": "equidistant", "none": "none"}
    if dist not in models:
        raise SourceError(
            f"{key}: distortion_model {dist!r} is not supported (radtan, equidistant, none)"
        )
    return CameraModel(
        width=_pixels(res[0], f"{key}.resolution[0]"),
        height=_pixels(res[1], f"{key}.resolution[1]"),
        K=np.array([fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]),
        D=_numbers(cam.get("distortion_coeffs") or [], f"{key}.distortion_coeffs"),
        distortion_model=models[dist],
    )


def _matrix(value: Any, name: str) -> F64:
    """An OpenCV matrix: ``{rows, cols, data}`` (FileStorage) or a (nested) list."""
    if isinstance(value, dict) and "data" in value:
        return _numbers(value["data"], f"{name}.data")
    if isinstance(value, list):
        value = np.asarray(value, dtype=object).reshape(-1).tolist()  # rows of a matrix
    return _numbers(value, name)


def _from_opencv(doc: dict[str, Any]) -> CameraModel:
    K = _matrix(next(doc[k] for k in _CV_MATRIX if k in doc), "camera_matrix")
    if K.size != 9:
        raise SourceError(f"camera_matrix has {K.size} numbers, needs 9")
    dkey = next((k for k in _CV_DIST if k in doc), None)
    D = _matrix(doc[dkey], dkey) if dkey is not None else np.zeros(0)
    size = doc.get("image_size") or doc.get("imageSize")
    res = doc.get("resolution")
    if "image_width" in doc and "image_height" in doc:
        w, h = doc["image_width"], doc["image_height"]
    elif isinstance(res, dict) and "width" in res and "height" in res:  # PhotonVision
        w, h = res["width"], res["height"]
    elif isinstance(size, list | tuple) and len(size) == 2:
        w, h = size
    else:
        raise SourceError(
            "no image size: an OpenCV calibration needs image_width and "
            "image_height (or image_size: [w, h])"
        )
    model = str(doc.get("distortion_model", "plumb_bob" if D.size <= 5 else "rational_polynomial"))
    if doc.get("fisheye") in (True, 1, "true"):
        model = "equidistant"
    return CameraModel(
        width=_pixels(w, "image_width"),
        height=_pixels(h, "image_height"),
        K=K,
        D=D,
        distortion_model=model,
    )


def _from_doc(doc: Any) -> CameraModel:
    if doc is None:
        raise SourceError(f"empty file; {_ROS_NEEDS}")
    if not isinstance(doc, dict):
        raise SourceError(
            f"not a camera_info YAML (it holds {type(doc).__name__}, not a mapping); {_ROS_NEEDS}"
        )
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
        raise SourceError(
            f"camera: no {', '.join(missing)} (the short form needs width, "
            "height, fx, fy, cx, cy and optionally distortion_model, "
            "distortion)"
        )
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

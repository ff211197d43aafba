"""Pinhole camera with ROS distortion models: pixels ↔ normalized coordinates.

Pixel convention: OpenCV/ROS (pixel centres at integer coordinates, origin at the top-left pixel's
centre), the convention of ``K`` in ``sensor_msgs/CameraInfo``. Points ``p_cam`` are in the
camera optical frame (x right, y down, z forward), metres. Normalized coordinates are
``(x/z, y/z)`` of the undistorted ray.

Distortion models (ROS names): ``plumb_bob`` (k1 k2 p1 p2 k3), ``rational_polynomial``
(k1 k2 p1 p2 k3 k4 k5 k6) — both OpenCV's Brown–Conrady model —, ``equidistant`` (k1..k4, OpenCV's
``cv2.fisheye``) and ``none``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike

from tagtrail.errors import SourceError
from tagtrail.geometry.arrays import F64

MODELS = ("plumb_bob", "rational_polynomial", "equidistant", "none")
_ALIASES = {"": "none", "fisheye": "equidistant", "radtan": "plumb_bob", "pinhole": "none"}
_OPENCV_NCOEF = (4, 5, 8, 12, 14)
MAX_SIDE_PX = 16384  # a larger camera is a corrupt message (its undistortion grid alone: GBs)
# Tight criteria: OpenCV's default (5 iterations) leaves ~1e-9 rad of error with strong distortion.
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Intrinsics of one camera, as in ``sensor_msgs/CameraInfo``.

    ``K``: (3, 3) camera matrix (px); ``D``: (n,) distortion coefficients in ROS order.
    """

    width: int
    height: int
    K: F64 = field(repr=False)
    D: F64 = field(repr=False)
    distortion_model: str = "plumb_bob"

    def __post_init__(self) -> None:
        model = _ALIASES.get(str(self.distortion_model).strip(), str(self.distortion_model).strip())
        if model not in MODELS:
            raise SourceError(
                f"unsupported distortion model {self.distortion_model!r} "
                f"(supported: {', '.join(MODELS)})"
            )
        K = np.array(self.K, dtype=np.float64).reshape(3, 3)
        D = np.array(self.D, dtype=np.float64).reshape(-1)
        if not np.isfinite(K).all():
            raise SourceError(f"camera matrix K has non-finite values: {K.reshape(-1).tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise SourceError(
                f"camera matrix K is not a calibration: fx = {K[0, 0]:g}, "
                f"fy = {K[1, 1]:g} (both must be > 0)"
            )
        if not np.isfinite(D).all():
            raise SourceError(f"distortion coefficients are not finite: {D.tolist()}")
        if abs(K[1, 0]) + abs(K[2, 0]) + abs(K[2, 1]) + abs(K[2, 2] - 1) > 1e-6:
            raise SourceError(
                f"camera matrix K is not [fx s cx, 0 fy cy, 0 0 1]: {K.reshape(-1).tolist()}"
            )
        if model not in ("equidistant", "none") and D.size > _OPENCV_NCOEF[-1]:
            raise SourceError(f"{D.size} distortion coefficients: OpenCV takes at most 14")
        w, h = self.width, self.height
        if not all(isinstance(v, int | np.integer) and 1 <= v <= MAX_SIDE_PX for v in (w, h)):
            raise SourceError(
                f"image size {w}x{h} is not a camera's (width and height: whole "
                f"pixels, 1 to {MAX_SIDE_PX})"
            )
        if model == "equidistant":
            D = np.concatenate([D, np.zeros(4)])[:4] if D.size != 4 else D
        elif model == "none":
            D = np.zeros(0)
        K.setflags(write=False)
        D.setflags(write=False)
        object.__setattr__(self, "distortion_model", model)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def focal_px(self) -> float:
        """Pixels per unit of normalised image coordinates (the mean focal length)."""
        return 0.5 * float(self.K[0, 0] + self.K[1, 1])

    # --- construction -----------------------------------------------------------------------

    @classmethod
    def from_camera_info(cls, msg: Any) -> CameraModel:
        """From a deserialized ``sensor_msgs/msg/CameraInfo`` (rosbags message, ROS 1 or 2)."""
        # ROS 1 spells the arrays K, D; ROS 2 k, d.
        return cls(
            width=int(msg.width),
            height=int(msg.height),
            K=np.asarray(_field(msg, "k"), dtype=np.float64),
            D=np.asarray(_field(msg, "d"), dtype=np.float64),
            distortion_model=str(msg.distortion_model),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (the ``extract.camera`` artifact)."""
        return {
            "width": self.width,
            "height": self.height,
            "distortion_model": self.distortion_model,
            "K": [float(v) for v in self.K.reshape(-1)],
            "D": [float(v) for v in self.D],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraModel:
        """Inverse of :meth:`to_dict`."""
        try:
            return cls(
                width=int(d["width"]),
                height=int(d["height"]),
                K=np.asarray(d["K"], dtype=np.float64),
                D=np.asarray(d.get("D", []), dtype=np.float64),
                distortion_model=str(d.get("distortion_model", "plumb_bob")),
            )
        except (KeyError, TypeError, ValueError) as err:
            raise SourceError(f"invalid camera description {d!r}: {err!r}") from err

    def scaled(self, width: int, height: int) -> CameraModel:
        """The same lens on a ``width x height`` sensor: ``K`` scaled per axis, ``D`` unchanged.

        Scaling is about the image's outer corner, ``(-0.5, -0.5)`` in OpenCV pixels, so a
        principal point ``c`` becomes ``(c + 0.5) s - 0.5``.
        """
        if width <= 0 or height <= 0:
            raise SourceError(f"cannot scale a camera to {width}x{height} pixels")
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :2] *= sx  # fx, skew
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return CameraModel(int(width), int(height), K, self.D, self.distortion_model)

    def value_key(self) -> tuple[object, ...]:
        """A hashable key of the calibration's values (instances compare by identity): for caches
        of per-camera tables."""
        return (self.width, self.height, self.distortion_model, self.K.tobytes(), self.D.tobytes())

    def same_as(self, other: CameraModel, rtol: float = 1e-9) -> bool:
        """Equal size, model and (to ``rtol``) coefficients."""
        return (
            (self.width, self.height, self.distortion_model)
            == (other.width, other.height, other.distortion_model)
            and self.D.shape == other.D.shape
            and np.allclose(self.K, other.K, rtol=rtol, atol=0)
            and np.allclose(self.D, other.D, rtol=rtol, atol=1e-15)
        )

    # --- geometry ---------------------------------------------------------------------------

    def _cv_D(self) -> F64:
        """Coefficients padded to a length OpenCV accepts."""
        if self.distortion_model == "none" or self.D.size == 0:
            return np.zeros(5)
        n = next((k for k in _OPENCV_NCOEF if k >= self.D.size), None)
        if n is None:
            raise SourceError(f"{self.D.size} distortion coefficients: OpenCV takes at most 14")
        return np.concatenate([self.D, np.zeros(n - self.D.size)])

    def undistort(self, px: ArrayLike) -> F64:
        """Distorted pixels ``(..., 2)`` → normalized undistorted coordinates ``(..., 2)``."""
        px = np.asarray(px, dtype=np.float64)
        shape = px.shape
        if shape[-1] != 2:
            raise ValueError(f"pixels must have shape (..., 2), got {shape}")
        if px.size == 0:
            return np.zeros(shape)
        pts = px.reshape(-1, 1, 2)
        if self.distortion_model == "none":
            h = np.concatenate([pts[:, 0], np.ones((pts.shape[0], 1))], axis=1)
            out = np.linalg.solve(self.K, h.T).T
            return (out[:, :2] / out[:, 2:]).reshape(shape)
        if self.distortion_model == "equidistant":
            und = cv2.fisheye.undistortPoints(pts, self.K, self.D, criteria=_CRITERIA)
        else:
            und = cv2.undistortPoints(pts, self.K, self._cv_D(), None, None, criteria=_CRITERIA)
        return np.asarray(und, dtype=np.float64).reshape(shape)

    def project(self, p_cam: ArrayLike) -> F64:
        """Points ``(..., 3)`` in the camera frame (m) → distorted pixels ``(..., 2)``.

        Vectorised numpy of OpenCV's models (``projectPoints``, ``fisheye.projectPoints``).
        """
        p = np.asarray(p_cam, dtype=np.float64)
        if p.shape[-1] != 3:
            raise ValueError(f"points must have shape (..., 3), got {p.shape}")
        x, y = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
        d = self.D
        if self.distortion_model == "equidistant":
            r = np.hypot(x, y)
            th = np.arctan(r)
            th2 = th * th
            thd = th * (1 + th2 * (d[0] + th2 * (d[1] + th2 * (d[2] + th2 * d[3]))))
            scale = np.divide(thd, r, out=np.ones_like(r), where=r > 1e-12)
            x, y = x * scale, y * scale
        elif self.distortion_model != "none" and d.size:
            if d.size > 8:  # thin-prism / tilted models: OpenCV itself
                return self._project_cv(p)
            k = np.concatenate([d, np.zeros(8 - d.size)])
            r2 = x * x + y * y
            radial = (1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))) / (
                1 + r2 * (k[5] + r2 * (k[6] + r2 * k[7]))
            )
            x, y = (
                x * radial + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x),
                y * radial + k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y,
            )
        K = self.K
        return np.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], axis=-1)

    def _project_cv(self, p: F64) -> F64:
        uv, _ = cv2.projectPoints(
            p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self._cv_D()
        )
        return np.asarray(uv, dtype=np.float64).reshape(p.shape[:-1] + (2,))


def _field(msg: Any, name: str) -> Any:
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())

"""Fast tag renderer: ideal pinhole canvas + one distortion remap.

Each frame: a precomputed background (floor below the horizon, the camera being level), walls as
near-clipped polygons, then every visible tag (with its white quiet zone) warped from a texture
whose resolution (texels per cell) matches its on-screen size, painter's order far to near. The
whole ideal canvas is then distorted with ONE ``cv2.remap`` through a map computed once: for each
distorted output pixel, its ideal (undistorted) pixel. Realism (blur, exposure/contrast, sensor
noise) is applied to the distorted image; noise comes from a seeded bank, so a seed fixes the
images. Pixels follow OpenCV's convention (centres at integer coordinates).

Tag texture orientation: OpenCV's 36h11 image is the official one rotated 180° (NOTES); the
official image, upright (row 0 = tag +y, column 0 = tag −x), puts the detector's corner 0 at the
tag frame's (−s/2, −s/2).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tagtrail.errors import SpecError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.se3 import inv
from tagtrail.sim.camera import undistort_grid
from tagtrail.sim.scene import Scene, Wall

NEAR_M = 0.05
QUIET_CELLS = 1  # white quiet zone around the 8x8-cell black square (cells)
INK, PAPER = 24, 236  # grey levels of the printed tag
_FAMILY = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
_NOISE_PAD = 61
MAX_TEXELS_PER_CELL = 96


@dataclass(frozen=True)
class Realism:
    """Image realism knobs.

    ``noise_sigma``: Gaussian sensor noise (grey levels); ``blur_sigma``: optical blur (px);
    ``exposure``: gain; ``contrast``: about mid-grey; ``exposure_jitter``: relative std of a slow
    per-frame gain drift.
    """

    noise_sigma: float = 2.0
    blur_sigma: float = 0.5
    exposure: float = 1.0
    contrast: float = 1.0
    exposure_jitter: float = 0.03

    def __post_init__(self) -> None:
        bad = [
            flag
            for flag, ok in (
                ("--image-noise", self.noise_sigma >= 0),
                ("--blur", self.blur_sigma >= 0),
                ("--exposure", self.exposure > 0),
                ("--contrast", self.contrast > 0),
                ("--exposure-jitter", 0 <= self.exposure_jitter < 1),
            )
            if not ok
        ]
        if bad:
            raise SpecError(
                f"invalid image realism option(s): {', '.join(bad)} "
                "(noise and blur >= 0, exposure and contrast > 0, jitter in [0, 1))"
            )


def tag_bits(tag_id: int) -> np.ndarray:
    """Official tag36h11 image with quiet zone, one pixel per cell, ``(10, 10)`` uint8 0/1."""
    if not 0 <= tag_id < len(_FAMILY.bytesList):
        raise SpecError(f"tag id {tag_id} is not in tag36h11 (0..{len(_FAMILY.bytesList) - 1})")
    img = np.rot90(cv2.aruco.generateImageMarker(_FAMILY, int(tag_id), 8, borderBits=1), 2)
    return np.pad((img > 127).astype(np.uint8), QUIET_CELLS, constant_values=1)


def clip_near(poly_cam: F64, near: float = NEAR_M) -> F64:
    """Clip a convex polygon ``(n, 3)`` (camera frame) to ``z >= near`` (Sutherland-Hodgman)."""
    out = []
    n = len(poly_cam)
    for i in range(n):
        a, b = poly_cam[i], poly_cam[(i + 1) % n]
        if a[2] >= near:
            out.append(a)
        if (a[2] >= near) != (b[2] >= near):
            out.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(out).reshape(-1, 3)


class Renderer:
    """Renders a scene's camera views at the camera's resolution (RGB uint8, OpenCV pixels)."""

    def __init__(self, scene: Scene, realism: Realism = Realism(), seed: int = 0) -> None:
        self.camera: CameraModel = scene.camera
        self.realism = realism
        cam = self.camera
        gx, gy = np.moveaxis(undistort_grid(cam), -1, 0)
        K = cam.K
        ideal = np.stack([K[0, 0] * gx + K[0, 1] * gy + K[0, 2], K[1, 1] * gy + K[1, 2]], -1)
        lo = np.floor(ideal.reshape(-1, 2).min(0)) - 2
        hi = np.ceil(ideal.reshape(-1, 2).max(0)) + 2
        self.offset = -lo  # ideal canvas pixel = ideal pixel + offset
        self.canvas_wh = (int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1)
        self.K_ideal = cam.K.copy()
        self.K_ideal[:2, 2] += self.offset
        m = (ideal + self.offset).astype(np.float32)
        self._map1, self._map2 = cv2.convertMaps(m[..., 0], m[..., 1], cv2.CV_16SC2)
        self._background = self._make_background()
        self._walls = scene.walls
        self._ids = scene.tag_ids
        self._scene_T_tags = scene.scene_T_tags
        outer = scene.tag_sizes * (8 + 2 * QUIET_CELLS) / 8  # edge with quiet zone (m)
        self._outer = outer
        sx, sy = np.array([-1.0, 1.0, 1.0, -1.0]), np.array([1.0, 1.0, -1.0, -1.0])
        # Texture corners (top-left, top-right, bottom-right, bottom-left) in each tag frame.
        self._quads_tag = np.stack(
            [np.outer(outer / 2, sx), np.outer(outer / 2, sy), np.zeros((len(outer), 4))], -1
        )
        self._bits = {int(i): tag_bits(int(i)) for i in self._ids}
        self._tex: dict[tuple[int, int], np.ndarray] = {}
        self._tex_bytes = 0
        rng = np.random.default_rng(seed)
        h, w = cam.height + _NOISE_PAD, cam.width + _NOISE_PAD
        bank = rng.standard_normal((h, w), dtype=np.float32) * realism.noise_sigma
        self._noise = np.round(bank).astype(np.int16)

    # --- ideal canvas -------------------------------------------------------------------------

    def _make_background(self) -> np.ndarray:
        w, h = self.canvas_wh
        horizon = self.K_ideal[1, 2]  # the camera is level: the horizon is the row through cy
        rows = np.arange(h, dtype=np.float64)
        below = np.clip((rows - horizon) / max(h - horizon, 1.0), 0.0, 1.0)
        col = np.where(rows < horizon, 200.0, 118.0 - 30.0 * below)
        return np.repeat(col[:, None], w, axis=1).astype(np.uint8)

    def _texture(self, tag_id: int, level: int) -> np.ndarray:
        key = (tag_id, level)
        tex = self._tex.get(key)
        if tex is None:
            n = self._bits[tag_id].shape[0] * level
            big = cv2.resize(self._bits[tag_id], (n, n), interpolation=cv2.INTER_NEAREST)
            tex = np.where(big > 0, PAPER, INK).astype(np.uint8)
            if self._tex_bytes > 256 * 2**20:  # bound the cache; textures are cheap to rebuild
                self._tex.clear()
                self._tex_bytes = 0
            self._tex[key] = tex
            self._tex_bytes += tex.nbytes
        return tex

    def _project(self, pts_cam: F64) -> F64:
        return (pts_cam[..., :2] / pts_cam[..., 2:3]) * self.K_ideal[[0, 1], [0, 1]] + (
            self.K_ideal[:2, 2]
        )

    def _draw_wall(self, canvas: np.ndarray, wall: Wall, cam_T_scene: F64) -> None:
        pts = wall.corners_scene @ cam_T_scene[:3, :3].T + cam_T_scene[:3, 3]
        poly = clip_near(pts)
        if len(poly) < 3:
            return
        px = np.round(self._project(poly) * 16).astype(np.int32)
        cv2.fillConvexPoly(canvas, px, int(wall.gray), cv2.LINE_AA, shift=4)

    def _draw_tag(self, canvas: np.ndarray, k: int, cam_T_tag: F64, quad_cam: F64) -> None:
        w, h = self.canvas_wh
        clipped = bool((quad_cam[:, 2] < NEAR_M).any())
        poly = clip_near(quad_cam) if clipped else quad_cam
        if len(poly) < 3:
            return
        px = self._project(poly)
        x0, y0 = np.maximum(np.floor(px.min(0)).astype(int) - 1, 0)
        x1, y1 = np.minimum(np.ceil(px.max(0)).astype(int) + 2, (w, h))
        if x1 <= x0 or y1 <= y0:
            return
        # Texels per cell = on-screen pixels per cell (shortest edge), rounded down: a texel then
        # spans >= 1 px, so bilinear sampling acts like pixel-area integration across edges
        # (no jaggies); corner accuracy then matches an 8x-supersampled render.
        edge = np.linalg.norm(px - np.roll(px, 1, axis=0), axis=1).min()
        cells = self._bits[int(self._ids[k])].shape[0]
        level = int(np.clip(edge // cells, 1, MAX_TEXELS_PER_CELL))
        tex = self._texture(int(self._ids[k]), level)
        n, s = tex.shape[0], self._outer[k]
        # texture pixel (u, v) -> tag plane (x, y) -> ideal canvas pixel (ROI-relative)
        A = np.array(
            [[s / n, 0.0, s / (2 * n) - s / 2], [0.0, -s / n, s / 2 - s / (2 * n)], [0.0, 0.0, 1.0]]
        )
        Hp = self.K_ideal @ np.column_stack([cam_T_tag[:3, 0], cam_T_tag[:3, 1], cam_T_tag[:3, 3]])
        roi_shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        M = roi_shift @ Hp @ A
        roi = canvas[y0:y1, x0:x1]
        if not clipped:
            cv2.warpPerspective(
                tex,
                M,
                (x1 - x0, y1 - y0),
                dst=roi,
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_TRANSPARENT,
            )
            return
        # Part of the tag is behind the near plane: rays of ROI pixels outside the clipped
        # polygon hit the tag plane behind the camera, so mask them out.
        tmp = roi.copy()
        cv2.warpPerspective(
            tex,
            M,
            (x1 - x0, y1 - y0),
            dst=tmp,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_TRANSPARENT,
        )
        mask = np.zeros_like(roi)
        cv2.fillConvexPoly(mask, np.round((px - (x0, y0)) * 16).astype(np.int32), 1, shift=4)
        np.copyto(roi, tmp, where=mask.astype(bool))

    def render_ideal(self, scene_T_cam: F64) -> np.ndarray:
        """Undistorted grey canvas (``canvas_wh``; ideal pixel = canvas pixel − ``offset``)."""
        canvas = self._background.copy()
        cam_T_scene = inv(scene_T_cam)
        wall_d = [
            np.linalg.norm(cam_T_scene[:3, :3] @ w.corners_scene.mean(0) + cam_T_scene[:3, 3])
            for w in self._walls
        ]
        for i in np.argsort(wall_d)[::-1]:
            self._draw_wall(canvas, self._walls[i], cam_T_scene)
        cam_T_tags = cam_T_scene @ self._scene_T_tags
        R, t = cam_T_tags[:, :3, :3], cam_T_tags[:, :3, 3]
        quads = np.einsum("mij,mkj->mki", R, self._quads_tag) + t[:, None, :]
        facing = np.einsum("mi,mi->m", R[:, :, 2], -t) > 0
        front = (quads[..., 2] > NEAR_M).any(axis=1)
        todo = np.flatnonzero(facing & front)
        for k in todo[np.argsort(-np.linalg.norm(t[todo], axis=1))]:  # painter's order
            self._draw_tag(canvas, int(k), cam_T_tags[k], quads[k])
        return canvas

    # --- sensor -------------------------------------------------------------------------------

    def render(
        self, scene_T_cam: F64, rng: np.random.Generator | None = None, gain: float = 1.0
    ) -> np.ndarray:
        """RGB image ``(H, W, 3)`` uint8 of the view from ``scene_T_cam``; noise drawn from ``rng``
        (None: no noise), ``gain`` multiplies the exposure."""
        gray = self.distort(self.render_ideal(scene_T_cam))
        r = self.realism
        if r.blur_sigma > 0:
            gray = cv2.GaussianBlur(gray, (0, 0), r.blur_sigma)
        if gain != 1.0 or r.exposure != 1.0 or r.contrast != 1.0:
            x = np.arange(256, dtype=np.float64)
            lut = ((x - 128.0) * r.contrast + 128.0) * r.exposure * gain
            gray = cv2.LUT(gray, np.clip(np.round(lut), 0, 255).astype(np.uint8))
        if rng is not None and r.noise_sigma > 0:
            oy, ox = rng.integers(0, _NOISE_PAD, size=2)
            crop = self._noise[oy : oy + self.camera.height, ox : ox + self.camera.width]
            gray = cv2.add(gray, crop, dtype=cv2.CV_8U)
        return cv2.cvtColor(gray, cv2.COLOR_GRAY2RGB)

    def distort(self, canvas: np.ndarray) -> np.ndarray:
        """Apply the lens distortion: ideal canvas → distorted image (one remap)."""
        return cv2.remap(canvas, self._map1, self._map2, cv2.INTER_LINEAR)

    def gains(self, n: int, rng: np.random.Generator) -> F64:
        """Per-frame exposure gains ``(n,)``: a slow drift (two random-phase sinusoids, periods
        ~3 s and ~8 s at 30 fps) of relative std ``exposure_jitter``."""
        k = np.arange(n, dtype=np.float64)
        ph = rng.uniform(0.0, 2 * np.pi, size=2)
        drift: F64 = np.sin(2 * np.pi * k / 90.0 + ph[0]) + np.sin(2 * np.pi * k / 237.0 + ph[1])
        return 1.0 + self.realism.exposure_jitter * drift

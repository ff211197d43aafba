"""An exact, slow, independent tag renderer: ground truth for corner accuracy at 0.01 px.

Each pixel is the mean of ``ss x ss`` stratified, jittered samples of the printed tag (ink 24,
paper 236, the 1-cell white quiet zone, ``background`` beyond), each sample's ray traced through
the lens (``CameraModel.undistort``) onto the tag plane; then a Gaussian optical blur. Unlike the
simulator's renderer (OpenCV warps: sample positions quantized to 1/32 px), nothing here is
quantized, so the projected corners are exact to ~1e-3 px.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.se3 import F64
from tagtrail.sim.render import INK, PAPER, tag_bits


def true_corners(camera: CameraModel, cam_T_tag: F64, size: float) -> F64:
    """The four corners ``(4, 2)`` of the black square in raw pixels (OpenCV convention)."""
    return camera.project(tag_corners([size])[0] @ cam_T_tag[:3, :3].T + cam_T_tag[:3, 3])


def render_tag(
    camera: CameraModel,
    cam_T_tag: F64,
    size: float,
    tag_id: int,
    rng: np.random.Generator,
    ss: int = 10,
    blur: float = 0.5,
    noise: float = 0.0,
    background: float = 90.0,
) -> NDArray[np.uint8]:
    """Grey image of one tag (black square of edge ``size`` m) at ``cam_T_tag``."""
    bits = tag_bits(tag_id)
    cell = size / 8
    half = 5 * cell  # 8 cells + the quiet zone each side
    R, t = cam_T_tag[:3, :3], cam_T_tag[:3, 3]
    outline = camera.project(tag_corners([2 * half])[0] @ R.T + t)
    w, h = camera.width, camera.height
    x0, y0 = np.maximum(np.floor(outline.min(0)) - 4, 0).astype(int)
    x1, y1 = np.minimum(np.ceil(outline.max(0)) + 4, (w - 1, h - 1)).astype(int)
    ys, xs = np.mgrid[y0 : y1 + 1, x0 : x1 + 1].astype(np.float64)
    normal = R[:, 2]
    acc = np.zeros(xs.shape)
    for i in range(ss):
        for j in range(ss):
            px = np.stack(
                [
                    xs + (j + rng.random(xs.shape)) / ss - 0.5,
                    ys + (i + rng.random(xs.shape)) / ss - 0.5,
                ],
                axis=-1,
            )
            xy = camera.undistort(px)
            ray = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
            hit = ray * ((normal @ t) / (ray @ normal))[..., None] - t
            uv = hit @ R  # tag frame
            col = np.floor((uv[..., 0] + half) / cell).astype(int)  # from the tag's -x side
            row = np.floor((half - uv[..., 1]) / cell).astype(int)  # from its +y side
            inside = (col >= 0) & (col < 10) & (row >= 0) & (row < 10)
            paper = bits[np.clip(row, 0, 9), np.clip(col, 0, 9)] > 0
            acc += np.where(inside, np.where(paper, PAPER, INK), background)
    img = np.full((h, w), background)
    img[y0 : y1 + 1, x0 : x1 + 1] = acc / ss**2
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    if noise > 0:
        img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def compose(images: list[NDArray[np.uint8]], background: float = 90.0) -> NDArray[np.uint8]:
    """One image of tags rendered apart (same background, far enough not to overlap)."""
    out = images[0].copy()
    for img in images[1:]:
        mask = img != np.uint8(round(background))
        out[mask] = img[mask]
    return out


# Cameras of the corner tests: the LIMO's calibration (NOTES.md), and a fisheye with its K.
K = np.array([[442.17, 0.0, 323.04], [0.0, 443.88, 246.51], [0.0, 0.0, 1.0]])
LIMO = CameraModel(640, 480, K, np.array([0.0449, -0.0770, 0.0025, 0.0012, 0.0]))
FISHEYE = CameraModel(640, 480, K, np.array([0.05, -0.01, 0.002, 0.0]), "equidistant")

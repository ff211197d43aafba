"""Sub-pixel re-fit of a tag's four corners to the image gradient along its outer border.

pupil-apriltags' corners are off by 0.04–0.1 px RMS even on an exact render (a bias of its edge
refinement, different corner to corner): enough to tilt a 0.16 m tag seen from 1.5 m by
0.2–1° out of plane, and the anchor tag's tilt tilts the whole map. Here each of the four edges
of the black square is fitted again as a straight line to the pixels of a thin band around it,
weighted by the image gradient across the edge (dark inside → bright outside), in *undistorted*
pixel coordinates so that lens distortion does not bend the edge; the corners are the
intersections of neighbouring lines, distorted back into the raw image. Measured on exact
renders (tests/io/test_corners.py): 0.011–0.016 px RMS, against 0.04–0.08 px for the detector.

Why this is unbiased: the gradient profile across a blurred step edge is symmetric about the
edge, so the gradient-weighted centroid across a band centred on the edge lies on it. Two
details keep it so on a pixel grid. Gradients are 2x2 differences at pixel corners, whose
profile (σ ≈ 0.75 px at 0.5 px blur) is narrow enough that a band of ±2.5 px holds all of it:
a hard band that cut into the wider central-difference profile kept a different share of it
on each side depending on the edge's sub-pixel phase — no average over phases along an
axis-aligned edge — and tilted frontal tags by ~0.1°. And only the positive lobe counts, with
the band kept inside one cell: the inner edge of the black border (black → data bits) and the
far side of the white quiet zone have the opposite sign.

The neighbouring edges. One cell inside the outer edge lies the border's inner edge (to the
data bits, white or black along it), one cell outside the quiet zone's outer edge (to whatever
lies beyond: a wall, the floor, more paper). When blur is not small next to a cell (1 px blur,
3-4 px cells: most tags beyond 2 m), their gradient lobes (opposite sign) reach into the band
and eat one side of the edge's own lobe: the edge moves by up to ~0.1 px, by a bias set by the
background and the tag's bits, so the same in every frame of that tag (bench/bench_corners.py:
corner RMS at 1 px blur 0.17 px, no better than the detector's). So each edge's intensity
profile is fitted (:func:`_profile_fit`): a pixel-integrated, Gaussian-blurred model of the
border (ink), the quiet zone, what lies beyond it and the six data cells along the inner edge,
their grey levels and the blur σ free, the three edges placed by the tag's homography from
the current corners; the neighbours' part of that model is taken out of the gradient and the
centroid fitted again, on a band one cell wide (:func:`_model_fit`, twice, each from the corners
of the one before). The centroid stays what locates the edge (the profile model's σ and the
edge's position trade off when the samples see one sub-pixel phase); the model only removes
what is not the edge. Rendered room frames (bench_corners): corner RMS 0.096 -> 0.092 px at
0.5 px blur, 0.172 -> 0.108 px at 1 px blur (4 DN noise), where what frames cannot average (a
tag's edge's mean offset) drops from 0.013 to 0.009 cells.

A tag is refined or left as the detector gave it: small tags (cells under ``MIN_CELL_PX``),
edges with too little support and re-fits that move a corner by more than ``MAX_SHIFT_PX`` keep
the detector's corners.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

from tagtrail.geometry.arrays import F64
from tagtrail.geometry.camera import CameraModel

CELLS = 8  # tag36h11: the black square is 8 cells wide (6 data + the 1-cell border each side)
# the shortest side's cells: oblique tags' foreshortened sides at 2-2.5 px re-fit to 0.13 px
# against the detector's 0.19 px (rendered hall); under 2 px the re-fit does worse
MIN_CELL_PX = 2.0
MAX_SHIFT_PX = 1.0
_ITERATIONS = 2
_MIN_SUPPORT = 12  # pixels per edge
_MAX_TURN_COS = float(np.cos(np.radians(10)))
_GRID_PX = 4  # spacing of the cached undistortion grid
_MAX_STEPS = 64  # columns (rows) sampled along an edge
# the intensity-profile fit (_model_fit)
_MODEL_MAX_CELL_PX = 10.0  # larger cells: the neighbours' lobes stay clear of the band (blur
# under ~1.6 px), the centroid alone is kept
_MODEL_PASSES = 2  # fits, each from the corners of the one before
_MODEL_ITERATIONS = (3, 1)  # Levenberg-Marquardt steps of the first fit, of the later ones
_MODEL_FIT_ITERATIONS = 2  # centroid iterations per pass, the neighbours taken out
_MODEL_STEPS = 16  # columns (rows) sampled along an edge for its profile
_MODEL_GRADIENT_STEPS = 64  # ... and for the gradient's centroid
_MODEL_BAND_CELLS = 1.5  # samples within this many cells of the edge (the middle of the data
_MODEL_BAND_MIN_PX, _MODEL_BAND_MAX_PX = 2.5, 5.0  # cells inside, of what lies beyond outside)
_MODEL_END_MIN_PX, _MODEL_END_MAX_PX = 3.0, 6.0  # samples this far from the edge's ends
_MODEL_SIGMA0_PX = 1.0
_MODEL_HALF_CELLS, _MODEL_HALF_MAX_PX = 1.0, 3.0  # the gradient's band, neighbours taken out
_MODEL_PRIOR = 1e-3  # per DN² of a level: ~ one sample's weight for a 30 DN deviation
_BLOCK_SAMPLES = 20000  # samples per block of the normal equations
_SQRT_2PI = float(np.sqrt(2 * np.pi))
_MODEL_SIGMA_PX = (0.2, 4.0)


_UNIT = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]], dtype=np.float32)
QUIET_SCALE = 10 / 8  # the white quiet zone: one cell around the 8-cell black square


def truncated(corners: F64, width: int, height: int) -> NDArray[np.bool_]:
    """Which tags ``(m, 4, 2)`` have their white quiet zone cut by the image border.

    The detector finds such tags with one edge on the border or short of it (a corner several
    pixels off); their poses are not to be trusted. The quiet zone's outline is the black
    square's mapped by the tag's homography, ``QUIET_SCALE`` times larger.
    """
    c = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
    out = np.zeros(len(c), dtype=bool)
    for k, quad in enumerate(c):
        if not np.isfinite(quad).all():
            out[k] = True
            continue
        H = cv2.getPerspectiveTransform(_UNIT, quad.astype(np.float32))
        zone = cv2.perspectiveTransform((_UNIT * QUIET_SCALE)[None], H)[0]
        out[k] = bool(
            (zone < -0.5).any()
            or (zone[:, 0] > width - 0.5).any()
            or (zone[:, 1] > height - 0.5).any()
        )
    return out


def refine_corners(gray: NDArray[np.uint8], corners: F64, camera: CameraModel | None) -> F64:
    """Re-fitted corners ``(m, 4, 2)`` (OpenCV pixel convention, raw image) of a frame's tags.

    ``corners``: ``(m, 4, 2)`` (or one tag's ``(4, 2)``), the detector's corners in OpenCV's
    convention, detector order. ``camera``: the lens (None: no distortion). A tag whose re-fit is
    not reliable keeps its corners.
    """
    c = np.array(corners, dtype=np.float64)
    out = refine_many([gray], [c.reshape(-1, 4, 2)], camera)[0]
    return out[0] if c.ndim == 2 else out


def refine_many(
    grays: list[NDArray[np.uint8]],
    corners: list[F64],
    camera: CameraModel | None,
    model: bool = True,
) -> list[F64]:
    """:func:`refine_corners` of several frames (``corners[i]``: ``(m_i, 4, 2)`` in
    ``grays[i]``) by one camera. All edges of all tags are fitted at once (per-edge sums by one
    ``reduceat``): numpy's per-call overhead is paid once a batch, not once a tag. ``model``
    False: the gradient's centroid fit alone, without the intensity-profile model that takes
    the neighbouring edges out (:func:`_model_fit`: ~90 % of the time)."""
    sizes = [len(np.asarray(c).reshape(-1, 4, 2)) for c in corners]
    c = np.concatenate(
        [np.asarray(x, dtype=np.float64).reshape(-1, 4, 2) for x in corners] + [np.zeros((0, 4, 2))]
    )
    out = c.copy()
    side = np.linalg.norm(np.roll(c, -1, axis=1) - c, axis=2).min(axis=1)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(c).all(axis=(1, 2)) & (side / CELLS >= MIN_CELL_PX)
    # band half-width across an edge: clear of the border's inner edge one cell in (px)
    half = np.clip(side / CELLS - 1.5, 1.5, 2.5)
    frame = np.repeat(np.arange(len(sizes)), sizes)
    sel = np.flatnonzero(ok)  # grouped by frame, in order
    parts = []
    for f in np.unique(frame[sel]):
        tags = sel[frame[sel] == f]
        edge, px, g = _border_pixels(grays[f], c[tags], half[tags])
        parts.append((edge + 4 * np.searchsorted(sel, tags[0]), px, g))
    if parts:
        edge, px, g = (np.concatenate(x) for x in zip(*parts, strict=True))
        if len(edge):
            refined, good = _fit(edge, px, g, c[sel], half[sel], camera)
            out[sel[good]] = refined[good]
            sel = sel[good & (side[sel] / CELLS < _MODEL_MAX_CELL_PX) & model]
            if len(sel):
                wide = np.clip(side[sel] / CELLS * _MODEL_HALF_CELLS, 1.5, _MODEL_HALF_MAX_PX)
                out[sel] = _model_fit(grays, frame[sel], out[sel], c[sel], wide, camera)
    return np.split(out, np.cumsum(sizes)[:-1]) if sizes else []


def _fit(
    edge: NDArray[np.intp],
    px: F64,
    g: F64,
    c: F64,
    half: F64,
    camera: CameraModel | None,
    iterations: int = _ITERATIONS,
) -> tuple[F64, NDArray[np.bool_]]:
    """Fit the ``4m`` edges of ``m`` quads ``c``; returns corners ``(m, 4, 2)`` and which are
    reliable ``(m,)``."""
    m = len(c)
    ne = 4 * m
    uc = _to_undistorted(c.reshape(-1, 2), camera).reshape(m, 4, 2)
    centre = uc.mean(axis=1, keepdims=True)
    a = (uc - centre).reshape(ne, 2)
    b = (np.roll(uc, -1, axis=1) - centre).reshape(ne, 2)
    u = _undistorted_grid(px, camera) - centre.reshape(m, 2)[edge // 4]  # centred per tag
    length = np.linalg.norm(b - a, axis=1)
    d = (b - a) / length[:, None]
    n = np.stack([d[:, 1], -d[:, 0]], axis=1)
    n *= np.where(np.einsum("ij,ij->i", n, a) < 0, -1.0, 1.0)[:, None]  # outward
    rho = np.einsum("ij,ij->i", n, a)
    h = np.repeat(half, 4)
    t = np.einsum("ij,ij->i", u - a[edge], d[edge])
    inside = (t > h[edge] + 1.5) & (t < length[edge] - h[edge] - 1.5)  # clear of other edges
    good = np.ones(ne, dtype=bool)
    # per-edge sums by one reduceat over samples grouped by edge (as _border_pixels makes them)
    count = np.bincount(edge, minlength=ne)
    start = np.minimum(np.cumsum(count) - count, max(len(edge) - 1, 0))
    assert np.all(np.diff(edge) >= 0), "samples must be grouped by edge"
    moments = np.column_stack([u, u * u, u[:, 0] * u[:, 1]])  # x, y, x², y², xy
    for _ in range(iterations):
        ne_ = n[edge]
        band = inside & (np.abs(np.einsum("ij,ij->i", u, ne_) - rho[edge]) <= h[edge])
        # gradient across the edge, positive lobe only (distortion's local twist of the
        # normal is negligible at this scale)
        wgt = np.maximum(np.einsum("ij,ij->i", g, ne_), 0.0) * band
        sums = np.add.reduceat(np.column_stack([band, wgt, wgt[:, None] * moments]), start)
        sums[count == 0] = 0.0
        support, total = sums[:, 0], sums[:, 1]
        good &= (support >= _MIN_SUPPORT) & (total > 0)
        total[~good] = 1.0
        mx, my, sxx, syy, sxy = (sums[:, 2:] / total[:, None]).T
        sxx, syy, sxy = sxx - mx * mx, syy - my * my, sxy - mx * my  # about the centroid
        along = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # direction of the largest spread
        n_new = np.stack([np.sin(along), -np.cos(along)], axis=1)
        turn = np.einsum("ij,ij->i", n_new, n)
        n_new *= np.where(turn < 0, -1.0, 1.0)[:, None]
        good &= np.abs(turn) >= _MAX_TURN_COS
        n = np.where(good[:, None], n_new, n)
        rho = np.where(good, n[:, 0] * mx + n[:, 1] * my, rho)
    # corner k of a tag = its edge k-1 ∩ edge k
    n = n.reshape(m, 4, 2)
    rho = rho.reshape(m, 4)
    n0, r0 = np.roll(n, 1, axis=1), np.roll(rho, 1, axis=1)
    det = n0[..., 0] * n[..., 1] - n0[..., 1] * n[..., 0]
    ok = good.reshape(m, 4).all(axis=1) & (np.abs(det) > 1e-6).all(axis=1)
    det[~ok] = 1.0
    out_u = (
        np.stack(
            [(r0 * n[..., 1] - rho * n0[..., 1]) / det, (n0[..., 0] * rho - n[..., 0] * r0) / det],
            axis=-1,
        )
        + centre
    )
    out = _to_distorted(out_u.reshape(-1, 2), camera).reshape(m, 4, 2)
    ok &= np.isfinite(out).all(axis=(1, 2))
    ok &= np.linalg.norm(out - c, axis=2).max(axis=1) <= MAX_SHIFT_PX
    return out, ok


def _model_fit(
    grays: list[NDArray[np.uint8]],
    frame: NDArray[np.intp],
    quads: F64,
    start: F64,
    half: F64,
    camera: CameraModel | None,
) -> F64:
    """Corners ``(m, 4, 2)`` of the tags ``quads`` (raw pixels; ``grays[frame[j]]``: tag j's image;
    ``start``: the detector's corners, for ``MAX_SHIFT_PX``; ``half``: the band) re-fitted by
    :func:`_fit` once the gradient of each edge's neighbouring edges — the border's inner edge
    and the quiet zone's outer edge, from a fit of the edge's intensity profile — is taken out
    (module docstring). A tag whose fit fails keeps ``quads``."""
    m = len(quads)
    out = quads.copy()
    ok = np.ones(m, dtype=bool)
    groups = [np.flatnonzero(frame == f) for f in np.unique(frame)]
    sigma = np.full(4 * m, _MODEL_SIGMA0_PX)
    for k in range(_MODEL_PASSES):
        geo = _edge_geometry(_to_undistorted(out.reshape(-1, 2), camera).reshape(m, 4, 2))
        band = np.clip(_MODEL_BAND_CELLS * geo["cell"], _MODEL_BAND_MIN_PX, _MODEL_BAND_MAX_PX)
        end = np.clip(geo["cell"], _MODEL_END_MIN_PX, _MODEL_END_MAX_PX)
        parts, grads = [], []
        for tags in groups:
            rows = (4 * tags[:, None] + np.arange(4)).ravel()
            gray = grays[frame[tags[0]]]
            e_rel, xs, ys = _edge_pixels(
                gray.shape, out[tags], end[rows], band[rows] + 1.0, 0.0, _MODEL_STEPS
            )
            parts.append(
                (
                    rows[e_rel],
                    np.stack([xs, ys], axis=1).astype(np.float64),
                    gray[ys, xs].astype(np.float64),
                )
            )
            e_rel, px, g = _border_pixels(gray, out[tags], half[tags], _MODEL_GRADIENT_STEPS)
            grads.append((rows[e_rel], px, g))
        edge, px, val = (np.concatenate(x) for x in zip(*parts, strict=True))
        order = np.argsort(edge, kind="stable")
        params, good = _profile_fit(
            edge[order],
            _undistorted_grid(px[order], camera),
            val[order],
            geo,
            band,
            sigma,
            _MODEL_ITERATIONS[min(k, 1)],
        )
        sigma = np.where(good, params[:, -1], sigma)
        edge, px, g = (np.concatenate(x) for x in zip(*grads, strict=True))
        order = np.argsort(edge, kind="stable")
        edge, px, g = edge[order], px[order], g[order]
        g_nb = _neighbours(edge, _undistorted_grid(px, camera), geo, params)
        g_nb = g_nb[:, None] * geo["n"][edge] * good[edge][:, None]
        refined, fitted = _fit(edge, px, g - g_nb, out, half, camera, _MODEL_FIT_ITERATIONS)
        ok &= fitted & good.reshape(m, 4).all(axis=1)
        ok &= np.linalg.norm(refined - start, axis=2).max(axis=1) <= MAX_SHIFT_PX
        out = np.where(ok[:, None, None], refined, out)
    return np.where(ok[:, None, None], out, quads)


def _neighbours(edge: NDArray[np.intp], u: F64, geo: dict[str, F64], params: F64) -> F64:
    """The neighbouring edges' part of the fitted intensity profiles (:func:`_profile_fit`'s
    ``params``) as a 1-px difference along the edge's outward normal — what a 2x2 gradient
    across the edge sees of them — at undistorted points ``u`` ``(n, 2)`` of ``edge`` (n,)."""
    n_lin = 3 + CELLS - 2
    q = params[edge]
    d_in = np.einsum("ij,ij->i", u, geo["n_in"][edge]) - geo["rho_in"][edge]
    d_q = np.einsum("ij,ij->i", u, geo["n_q"][edge]) - geo["rho_q"][edge]
    t = np.einsum("ij,ij->i", u - geo["a"][edge], geo["d"][edge])
    sigma = q[:, -1:]
    F = _step(np.stack([d_q + 0.5, d_q - 0.5, -d_in - 0.5, -d_in + 0.5], axis=1), sigma)[0]
    Fb = _step(t[:, None] - geo["t_cells"][edge], sigma)[0]
    data = np.einsum("ij,ij->i", Fb[:, :-1] - Fb[:, 1:], q[:, 3:n_lin])
    out: F64 = q[:, 2] * (F[:, 0] - F[:, 1]) + (F[:, 2] - F[:, 3]) * data
    return out


def _intersect(n: F64, rho: F64) -> F64:
    """Corner k = line k-1 ∩ line k of ``(m, 4)`` lines ``n · u = rho``; NaN where parallel."""
    n0, r0 = np.roll(n, 1, axis=1), np.roll(rho, 1, axis=1)
    det = n0[..., 0] * n[..., 1] - n0[..., 1] * n[..., 0]
    det = np.where(np.abs(det) > 1e-6, det, np.nan)
    return np.stack(
        [(r0 * n[..., 1] - rho * n0[..., 1]) / det, (n0[..., 0] * rho - n[..., 0] * r0) / det],
        axis=-1,
    )


def _edge_geometry(uc: F64) -> dict[str, F64]:
    """Per edge ``4 j + k`` of the quads ``uc`` ``(m, 4, 2)`` (undistorted px): its start corner
    ``a``, unit direction ``d``, ``length``, outward unit normal ``n`` and the lines (``n_in``,
    ``rho_in``; ``n_q``, ``rho_q``: ``n · u = rho``, normals outward) of the border's inner edge
    (one cell in) and of the quiet zone's outer edge (one cell out), ``cell`` (px across the edge
    at its middle) and ``t_cells`` ``(E, 7)``: where the six data cells along the border's inner
    edge begin and end, as distances along the edge from ``a`` — all through the tag's
    homography."""
    m = len(uc)
    H = _homographies(uc)

    def edges(scale: float) -> tuple[F64, F64]:
        p = _apply(H, np.broadcast_to(_UNIT * scale, (m, 4, 2)))
        q = np.roll(p, -1, axis=1)
        return p.reshape(-1, 2), q.reshape(-1, 2)

    a, b = edges(1.0)
    length = np.linalg.norm(b - a, axis=1)
    d = (b - a) / length[:, None]
    n = np.stack([d[:, 1], -d[:, 0]], axis=1)
    centre = np.repeat(uc.mean(axis=1), 4, axis=0)
    n *= np.where(np.einsum("ij,ij->i", n, a - centre) < 0, -1.0, 1.0)[:, None]
    out = {"a": a, "d": d, "length": length, "n": n}
    for name, scale in (("in", (CELLS - 2) / CELLS), ("q", (CELLS + 2) / CELLS)):
        p, q = edges(scale)
        v = q - p
        nl = np.stack([v[:, 1], -v[:, 0]], axis=1) / np.linalg.norm(v, axis=1)[:, None]
        nl *= np.where(np.einsum("ij,ij->i", nl, n) < 0, -1.0, 1.0)[:, None]
        out[f"n_{name}"], out[f"rho_{name}"] = nl, np.einsum("ij,ij->i", nl, p)
    mid = a + 0.5 * (b - a)
    out["cell"] = np.einsum("ij,ij->i", out["n_in"], mid) - out["rho_in"]
    k = np.arange(CELLS - 1) / (CELLS - 2)  # the data cells' boundaries on the inner edge
    lo, hi = _UNIT * (CELLS - 2) / CELLS, np.roll(_UNIT, -1, axis=0) * (CELLS - 2) / CELLS
    pts = lo[:, None, :] + (hi - lo)[:, None, :] * k[None, :, None]  # (4, 7, 2)
    img = _apply(H, np.broadcast_to(pts.reshape(1, -1, 2), (m, 4 * (CELLS - 1), 2)))
    img = img.reshape(4 * m, CELLS - 1, 2)
    out["t_cells"] = np.einsum("eki,ei->ek", img - a[:, None, :], d)
    return out


def _homographies(uc: F64) -> F64:
    """``(m, 3, 3)`` homographies taking ``_UNIT`` to the quads ``uc`` ``(m, 4, 2)`` (DLT)."""
    m = len(uc)
    x, y = (np.broadcast_to(_UNIT[:, i].astype(np.float64), (m, 4)) for i in (0, 1))
    u, v = uc[..., 0], uc[..., 1]
    z, o = np.zeros((m, 4)), np.ones((m, 4))
    A = np.concatenate(
        [
            np.stack([x, y, o, z, z, z, -u * x, -u * y], axis=-1),
            np.stack([z, z, z, x, y, o, -v * x, -v * y], axis=-1),
        ],
        axis=1,
    )
    rhs = np.concatenate([u, v], axis=1)
    with np.errstate(all="ignore"):
        h = np.linalg.solve(A + 0.0, rhs[..., None])[..., 0] if m else np.zeros((0, 8))
    return np.concatenate([h, np.ones((m, 1))], axis=1).reshape(m, 3, 3)


def _apply(H: F64, p: F64) -> F64:
    """Points ``p`` ``(m, k, 2)`` mapped by ``H`` ``(m, 3, 3)``."""
    q = np.einsum("mij,mkj->mki", H[:, :, :2], p) + H[:, None, :, 2]
    out: F64 = q[..., :2] / q[..., 2:]
    return out


def _profile_fit(
    edge: NDArray[np.intp],
    u: F64,
    val: F64,
    geo: dict[str, F64],
    band: F64,
    sigma0: F64,
    iterations: int,
) -> tuple[F64, NDArray[np.bool_]]:
    """Levenberg–Marquardt fit of each edge's intensity profile about its current line
    (samples ``val`` at undistorted ``u`` ``(n, 2)``, grouped by ``edge``): the grey levels of
    the border (ink), the quiet zone, what lies beyond it and the six data cells, and a common
    Gaussian blur σ (px; the pixel's footprint apart; from ``sigma0`` (E,), ``iterations``
    steps). Returns ``(E, 10)`` parameters [ink,
    quiet - ink, beyond - quiet, data cells - ink (6), σ] and which edges fitted."""
    ne = len(geo["n"])
    d = np.einsum("ij,ij->i", u, geo["n"][edge]) - np.einsum("ij,ij->i", geo["a"], geo["n"])[edge]
    keep = np.abs(d) <= band[edge]
    edge, u, d, val = edge[keep], u[keep], d[keep], val[keep]
    d_in = np.einsum("ij,ij->i", u, geo["n_in"][edge]) - geo["rho_in"][edge]
    d_q = np.einsum("ij,ij->i", u, geo["n_q"][edge]) - geo["rho_q"][edge]
    dt = np.einsum("ij,ij->i", u - geo["a"][edge], geo["d"][edge])[:, None] - geo["t_cells"][edge]
    count = np.bincount(edge, minlength=ne)
    starts = np.minimum(np.cumsum(count) - count, max(len(edge) - 1, 0))
    n_lin = 3 + CELLS - 2
    params = np.zeros((ne, n_lin + 1))
    params[:, -1] = sigma0
    x3 = np.stack([d, d_q, -d_in], axis=1)

    def evaluate(p: F64, jacobian: bool) -> tuple[F64, F64 | None]:
        q = p[edge]
        sigma = q[:, -1:]
        F, g_sig = _step(x3, sigma)
        Fb, gb_sig = _step(dt, sigma)
        b = Fb[:, :-1] - Fb[:, 1:]  # (n, 6): each data cell's share, blurred along the edge
        lv = q[:, 3:n_lin]
        data = np.einsum("ij,ij->i", b, lv)
        model = q[:, 0] + q[:, 1] * F[:, 0] + q[:, 2] * F[:, 1] + F[:, 2] * data
        if not jacobian:
            return model, None
        dsig = (
            q[:, 1] * g_sig[:, 0]
            + q[:, 2] * g_sig[:, 1]
            + g_sig[:, 2] * data
            + F[:, 2] * np.einsum("ij,ij->i", gb_sig[:, :-1] - gb_sig[:, 1:], lv)
        )
        J = np.column_stack([np.ones_like(d), F[:, 0], F[:, 1], F[:, 2:3] * b, dsig])
        return model, J

    # a weak prior holds the levels beyond the quiet zone and of the data cells at "no edge
    # there" where the band barely reaches them (large cells)
    prior = np.zeros(n_lin + 1)
    prior[2:n_lin] = _MODEL_PRIOR

    def cost(p: F64) -> F64:
        r = val - evaluate(p, False)[0]
        c: F64 = np.add.reduceat(r * r, starts) + (prior * p * p).sum(axis=1)
        c[count == 0] = np.inf
        return c

    if not len(edge):
        return params, np.zeros(ne, dtype=bool)
    _, J = evaluate(params, True)  # start: the levels by least squares at the starting σ
    assert J is not None
    JtJ, Jtr = _normal(J[:, :n_lin], val, starts, count)
    params[:, :n_lin] = _ridge_solve(JtJ + np.diag(prior[:n_lin]), Jtr)
    current = cost(params)
    lam = np.full(ne, 1e-3)
    for _ in range(iterations):
        model, J = evaluate(params, True)
        assert J is not None
        JtJ, Jtr = _normal(J, val - model, starts, count)
        JtJ += np.diag(prior)
        Jtr -= prior * params
        diag = np.einsum("eii->ei", JtJ)
        step = _ridge_solve(JtJ + lam[:, None, None] * np.eye(n_lin + 1) * diag[:, None, :], Jtr)
        trial = params + step
        trial[:, -1] = np.clip(trial[:, -1], _MODEL_SIGMA_PX[0], _MODEL_SIGMA_PX[1])
        c = cost(trial)
        better = c < current
        params = np.where(better[:, None], trial, params)
        current = np.where(better, c, current)
        lam = np.where(better, lam / 3, lam * 4)
    sigma = params[:, -1]
    good = (
        (count >= _MIN_SUPPORT)
        & np.isfinite(current)
        & np.isfinite(params).all(axis=1)
        & (sigma > _MODEL_SIGMA_PX[0])
        & (sigma < _MODEL_SIGMA_PX[1])
        & (params[:, 1] > 0)
    )
    return params, good


def _normal(J: F64, r: F64, starts: NDArray[np.intp], count: NDArray[np.intp]) -> tuple[F64, F64]:
    """Per-edge ``JᵀJ`` ``(E, k, k)`` and ``Jᵀr`` ``(E, k)`` of samples grouped by edge
    (``starts``, ``count``), in blocks of edges (bounded memory)."""
    ne, k = len(count), J.shape[1]
    JtJ, Jtr = np.zeros((ne, k, k)), np.zeros((ne, k))
    e0 = 0
    while e0 < ne:
        end = np.cumsum(count[e0:])
        e1 = e0 + max(1, int(np.searchsorted(end, _BLOCK_SAMPLES, side="right")))
        lo, hi = int(starts[e0]), int(starts[e0] + count[e0:e1].sum())
        if hi > lo:
            Jb = J[lo:hi]
            idx = starts[e0:e1] - lo
            has = count[e0:e1] > 0
            idx = np.minimum(idx, hi - lo - 1)
            outer = np.add.reduceat(Jb[:, :, None] * Jb[:, None, :], idx, axis=0)
            JtJ[e0:e1][has] = outer[has]
            Jtr[e0:e1][has] = np.add.reduceat(Jb * r[lo:hi, None], idx, axis=0)[has]
        e0 = e1
    JtJ[count == 0] = np.eye(k)
    return JtJ, Jtr


def _pixel_step(x: F64, sigma: F64) -> tuple[F64, F64, F64]:
    """A unit step at 0 blurred by a Gaussian of ``sigma`` px and averaged over a pixel (a box
    of 1 px across the edge: the pixel's footprint has that variance in every direction), at
    ``x`` px; with its derivatives in ``x`` and in ``sigma``. ∫Φ = zΦ(z) + φ(z)."""
    zp, zm = (x + 0.5) / sigma, (x - 0.5) / sigma
    Fp, Fm = ndtr(zp), ndtr(zm)
    fp, fm = np.exp(-0.5 * zp * zp) / _SQRT_2PI, np.exp(-0.5 * zm * zm) / _SQRT_2PI
    return sigma * (zp * Fp + fp - zm * Fm - fm), Fp - Fm, fp - fm


def _step(x: F64, sigma: F64) -> tuple[F64, F64]:
    """:func:`_pixel_step`'s value and σ-derivative, computed only where the step is not yet
    flat (|x| < 5 σ + 1: elsewhere 0 or 1, derivative 0); ``sigma`` broadcasts to ``x``."""
    sig = np.broadcast_to(sigma, x.shape)
    near = np.abs(x) < 5.0 * sig + 1.0
    F, F_sig = (x > 0).astype(np.float64), np.zeros(x.shape)
    F[near], _, F_sig[near] = _pixel_step(x[near], sig[near])
    return F, F_sig


def _ridge_solve(A: F64, b: F64) -> F64:
    """Batched ``A x = b`` with a tiny ridge (levels of data cells no sample sees stay 0)."""
    k = A.shape[-1]
    scale = np.maximum(np.einsum("eii->e", A) / k, 1e-12)
    x: F64 = np.linalg.solve(A + 1e-9 * scale[:, None, None] * np.eye(k), b[..., None])[..., 0]
    return x


def _border_pixels(
    gray: NDArray[np.uint8], quads: F64, half: F64, max_steps: int = _MAX_STEPS
) -> tuple[NDArray[np.intp], F64, F64]:
    """Gradient samples near the raw edges of ``quads`` ``(m, 4, 2)`` — within the band, the
    largest shift and the bending by distortion: edge index ``4 j + k`` (n,), position ``px``
    (n, 2) and gradient ``g`` (n, 2), 2x2 differences at pixel corners (x + ½, y + ½)."""
    reach = np.repeat(half, 4) + MAX_SHIFT_PX + 0.5
    edge, xs, ys = _edge_pixels(gray.shape, quads, np.repeat(half, 4), reach, 0.5, max_steps)
    i00 = gray[ys, xs].astype(np.float64)
    i01 = gray[ys, xs + 1].astype(np.float64)
    i10 = gray[ys + 1, xs].astype(np.float64)
    i11 = gray[ys + 1, xs + 1].astype(np.float64)
    gx = 0.5 * ((i01 - i00) + (i11 - i10))
    gy = 0.5 * ((i10 - i00) + (i11 - i01))
    px = np.stack([xs, ys], axis=1).astype(np.float64) + 0.5
    return edge, px, np.stack([gx, gy], axis=1)


def _edge_pixels(
    shape: tuple[int, ...],
    quads: F64,
    end: F64,
    reach: F64,
    at: float,
    max_steps: int = _MAX_STEPS,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Pixels ``(x, y)`` whose point ``(x + at, y + at)`` lies within ``reach`` (E,) px of the
    raw edges of ``quads`` ``(m, 4, 2)`` and more than ``end`` (E,) px from their ends (edge
    ``4 j + k`` from corner k to k + 1), with the 2x2 block at ``(x, y)`` (``at`` = ½) or the
    pixel (``at`` = 0) inside the image: edge index, x, y (n,), grouped by edge.

    Along each edge at most ``max_steps`` columns (or rows, whichever the edge is closer to)
    are taken: the cost of a tag does not grow with its size.
    """
    h, w = shape[:2]
    a = quads.reshape(-1, 2)
    d = np.roll(quads, -1, axis=1).reshape(-1, 2) - a
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    major = (np.abs(d[:, 1]) > np.abs(d[:, 0])).astype(np.intp)  # 0: x, 1: y
    rows = np.arange(len(a))
    a_major, d_major = a[rows, major], d[rows, major]
    lo = np.ceil(np.minimum(a_major, a_major + d_major))
    span = np.floor(np.maximum(a_major, a_major + d_major)) - lo + 1
    steps = np.clip(span, 1, max_steps)
    i = np.arange(max_steps)
    # one column per stratum of span / steps (>= 1) columns, at a golden-ratio offset within it:
    # regular strides would alias with the edge's slope and sample few sub-pixel phases
    jitter = (i * 0.6180339887498949) % 1.0
    along = lo[:, None] + np.floor((i + jitter) * span[:, None] / steps[:, None])  # (E, S)
    centre = (
        a[rows, 1 - major][:, None]
        + (along - a_major[:, None]) * (d[rows, 1 - major] / d_major)[:, None]
    )
    cos = np.abs(d_major) / length  # >= 1/√2: the edge is within 45° of its axis
    r = int(np.ceil((reach / cos).max())) + 1
    across = np.floor(centre)[:, :, None] + np.arange(-r, r + 1)  # (E, S, 2r+1)
    along = np.broadcast_to(along[:, :, None], across.shape)
    is_x = (major == 0)[:, None, None]
    xs, ys = np.where(is_x, along, across), np.where(is_x, across, along)
    px_, py_ = xs + at - a[:, 0, None, None], ys + at - a[:, 1, None, None]
    t = px_ * u[:, 0, None, None] + py_ * u[:, 1, None, None]
    off = np.abs(px_ * u[:, 1, None, None] - py_ * u[:, 0, None, None])
    hh = end[:, None, None]
    last = 2 if at else 1
    keep = (
        (i < steps[:, None])[:, :, None]
        & (off <= reach[:, None, None])
        & (t > hh)
        & (t < length[:, None, None] - hh)
        & (xs >= 0)
        & (xs <= w - last)
        & (ys >= 0)
        & (ys <= h - last)
    )
    edge = np.broadcast_to(rows[:, None, None], keep.shape)[keep]
    return edge, xs[keep].astype(np.intp), ys[keep].astype(np.intp)


def _to_undistorted(px: F64, camera: CameraModel | None) -> F64:
    """Raw pixels → undistorted pixels (the same K, no distortion), exact."""
    if camera is None or camera.distortion_model == "none":
        return px
    return _k_pixels(camera.undistort(px), camera.K)


def _undistorted_grid(px: F64, camera: CameraModel | None) -> F64:
    """:func:`_to_undistorted` of many pixels: bilinear in a cached grid of ``_GRID_PX``
    spacing, then a fixed-point step on the forward model (< 1e-3 px for the LIMO's lens; the
    grid alone is 0.007 px off at the image corners — the size of the biases that matter)."""
    if camera is None or camera.distortion_model == "none":
        return px
    grid = _grid(camera)
    q = np.clip(px / _GRID_PX, 0, np.array(grid.shape[1::-1]) - 1.000001)
    i0 = q.astype(np.intp)
    f = q - i0
    x0, y0 = i0[:, 0], i0[:, 1]
    fx, fy = f[:, :1], f[:, 1:]
    top = grid[y0, x0] * (1 - fx) + grid[y0, x0 + 1] * fx
    bottom = grid[y0 + 1, x0] * (1 - fx) + grid[y0 + 1, x0 + 1] * fx
    und = top * (1 - fy) + bottom * fy
    und += px - _to_distorted(und, camera)
    return und


_GRIDS: dict[tuple[object, ...], F64] = {}


def _grid(camera: CameraModel) -> F64:
    key = camera.value_key()
    grid = _GRIDS.get(key)
    if grid is None:
        nx, ny = -(-(camera.width - 1) // _GRID_PX) + 1, -(-(camera.height - 1) // _GRID_PX) + 1
        ys, xs = np.mgrid[0:ny, 0:nx] * _GRID_PX
        nodes = np.stack([xs, ys], axis=-1).reshape(-1, 2).astype(np.float64)
        grid = _GRIDS[key] = _to_undistorted(nodes, camera).reshape(ny, nx, 2)
    return grid


def _k_pixels(xy: F64, K: F64) -> F64:
    return np.stack(
        [K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]], axis=1
    )


def _to_distorted(u: F64, camera: CameraModel | None) -> F64:
    if camera is None or camera.distortion_model == "none":
        return u
    K = camera.K
    y = (u[:, 1] - K[1, 2]) / K[1, 1]
    x = (u[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return camera.project(np.stack([x, y, np.ones_like(x)], axis=1))

"""Holes, slots and trim edges measured on the part, after the fit, in the CAD frame.

A stereo cloud is blind at a part's outline: window matching loses the
points within about half a window of an edge, so a hole's rim taken from
the cloud comes out too large and a trim edge too short. The flash images
show the outline sharply, so the outline is measured in them:

1. the nominal outline (a hole's rim, or the CAD's boundary near a trim-edge
   point) is sampled in the CAD frame and carried into each camera that
   faces it by the fit's pose;
2. along each sample's in-plane normal, projected into the image, the grey
   profile is read at sub-pixel steps from the air into the material and
   fitted by an edge model: the air's level, then from the edge on the
   material's light blurred by the camera, where that light is the flash's
   slide as it falls on the surface there (predicted from the projector and
   the surface's plane, up to a gain) plus an unpatterned part (stray light,
   the metal's sheen). The speckle's grain is as fine as the blur, so an edge
   model that takes the material as even, or as a ramp, moves the edge
   wherever a grain meets the rim. The edge is where the
   model fits best over a fixed window, moved by the bias a curved outline's
   blur gives (half the blur's variance times the curvature, towards the
   air's convex side); saturated profiles, faint steps and air that is not
   dark (the belt lit through the hole) are dropped;
3. each edge pixel's ray is intersected with the surface's tangent plane at
   its sample, moved along the normal by the cloud's own offset there (the
   surface as measured, not as drawn);
4. a hole's rim points are fitted by a slot (two half circles joined by
   straight sides, a circle when its length is zero) in the hole's plane by
   robust least squares; a trim edge's points are fitted by a smooth curve
   (:mod:`inspection.edge_curve`), whose offset normal to the edge is averaged
   over the measured span, and whose largest offset is the edge's shape.

Each result carries its uncertainty (1 sigma, from the residual scatter)
and its support (the edge points used). :func:`hole_from_cloud` measures a
hole from the cloud alone, for comparison and where no images exist.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from .arrays import Image, Points, Scalars, Transform
from .edge_curve import CurveParams, EdgeCurve, curve_offset, nominal_curve
from .errors import InvalidInput
from .rig import Camera, Projector
from .transforms import apply

log = logging.getLogger(__name__)

__all__ = [
    "EdgeParams",
    "Flash",
    "HoleMeasurement",
    "HoleSpec",
    "TrimMeasurement",
    "hole_from_cloud",
    "hole_frame",
    "measure_hole",
    "measure_trim_edge",
    "rim_points",
    "boundary_samples",
]

# The profile is read every quarter pixel; the model is evaluated every fifth.
_PROFILE_STEP_PX = 0.25
_MODEL_STEP_PX = 0.2
# A profile whose air is brighter than the feature's typical air by more than this
# fraction of its step does not see the rim against the shadowed belt.
_AIR_FRACTION = 0.2
# A profile reaching this grey value is clipped: the sensor's saturation is no step.
_SATURATED_DN = 250.0
# The slide across the edge is averaged with the blur's along the edge (Gauss-Hermite
# nodes at 0 and +-sqrt(3) sigma, for a blur of this sigma).
_ALONG_SIGMA_PX = 0.75
# Neighbouring samples within this distance give a sample's outline curvature.
_CURVATURE_REACH_MM = 2.5


@dataclass(frozen=True)
class EdgeParams:
    """How edges are searched in the images.

    Attributes
    ----------
    search_px : float
        The edge is looked for this far on either side of the nominal outline
        (a hole shifted by up to about this many pixels is still found).
    window_px : float
        The edge model is fitted to the profile this far on either side of
        the nominal outline, the same window for every place of the edge, so
        that their fits compare.
    blur_px : tuple of float
        The camera's blur across the edge (Gaussian sigma, pixels, with the
        pixel's area and the profile's interpolation) is the one of these that
        fits a camera's profiles best.
    min_step_dn : float
        A profile whose material is fainter than this at the edge (over the
        air) is dropped: a dark speckle grain on the rim leaves it no step.
    sample_mm : float
        Spacing of the outline's samples.
    min_cos : float
        A camera sees a sample when the cosine between the surface normal and
        the direction to the camera is at least this.
    reject_sigma : float
        Edge points farther than this many robust sigmas from the fit are
        dropped, and the fit repeated.
    """

    search_px: float = 2.5
    window_px: float = 5.0
    blur_px: tuple[float, ...] = (0.6, 0.7, 0.8, 0.9, 1.0)
    min_step_dn: float = 20.0
    sample_mm: float = 0.5
    min_cos: float = 0.3
    reject_sigma: float = 3.0


@dataclass(frozen=True, eq=False)
class Flash:
    """The flash's slide, as the edge model predicts the light on the part.

    Build it once per rig (:meth:`build` renders the slide).

    Attributes
    ----------
    projector : Projector
    slide : (H, W) float32
        The slide's relative intensity (:meth:`Pattern.image <inspection.rig.Pattern.image>`).
    """

    projector: Projector
    slide: npt.NDArray[np.float32]

    @classmethod
    def build(cls, projector: Projector) -> Flash:
        """The projector's slide, rendered."""
        if not isinstance(projector, Projector):
            raise InvalidInput(f"a Flash needs a Projector, got {type(projector).__name__}")
        slide = projector.pattern.image(projector.width, projector.height)
        return cls(projector, np.ascontiguousarray(slide, dtype=np.float32))

    def along(
        self,
        camera: Camera,
        uv0: npt.NDArray[np.float64],
        step: npt.NDArray[np.float64],
        t: npt.NDArray[np.float64],
        plane_points: Points,
        plane_normals: Points,
    ) -> npt.NDArray[np.float32]:
        """The slide's intensity on the surface seen along image lines.

        Parameters
        ----------
        camera : the camera of the image
        uv0 : (N, 2) float64, pixels
            Where each line passes.
        step : (N, 2) float64
            Unit image directions of the lines.
        t : (M,) float64, pixels
            Places along the lines.
        plane_points, plane_normals : (N, 3) float64, rig frame
            The surface's plane under each line.

        Returns
        -------
        (N, M) float32
            The slide at ``uv0 + t * step`` where the pixel's ray meets the
            plane, averaged along the edge (across the line) over the camera's
            blur.
        """
        n = len(uv0)
        across = np.column_stack([-step[:, 1], step[:, 0]])
        # The map from a line's place to the slide is smooth (a homography through the
        # lens's distortion): exact at three places, quadratic between.
        knots = np.array([t[0], 0.5 * (t[0] + t[-1]), t[-1]])
        # (3, M): the knots' Lagrange weights at each t.
        lag = np.stack([(t - knots[1]) * (t - knots[2]), (t - knots[0]) * (t - knots[2]),
                        (t - knots[0]) * (t - knots[1])])  # fmt: skip
        lag /= np.array([(knots[0] - knots[1]) * (knots[0] - knots[2]),
                         (knots[1] - knots[0]) * (knots[1] - knots[2]),
                         (knots[2] - knots[0]) * (knots[2] - knots[1])])[:, None]  # fmt: skip
        out = np.zeros((n, len(t)), np.float32)
        node = math.sqrt(3.0) * _ALONG_SIGMA_PX
        for off, weight in ((0.0, 2 / 3), (node, 1 / 6), (-node, 1 / 6)):
            uv = uv0[:, None, :] + knots[None, :, None] * step[:, None, :]
            uv = uv + off * across[:, None, :]
            origin, direction = camera.rays(uv.reshape(-1, 2))
            q = np.repeat(plane_points, 3, axis=0)
            nrm = np.repeat(plane_normals, 3, axis=0)
            lam = np.einsum("ij,ij->i", q - origin, nrm) / np.einsum("ij,ij->i", direction, nrm)
            slide_uv = self.projector.project(origin + lam[:, None] * direction).reshape(n, 3, 2)
            at = np.einsum("am,nak->nmk", lag, slide_uv)
            out += np.float32(weight) * cv2.remap(
                self.slide,
                at[..., 0].astype(np.float32),
                at[..., 1].astype(np.float32),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0.0,
            )
        return out


@dataclass(frozen=True)
class HoleSpec:
    """A nominal hole or slot in the CAD frame.

    Attributes
    ----------
    centre : (3,) tuple of float, mm
        On the surface.
    normal : (3,) tuple of float
        The surface normal there (the hole's axis), towards the cameras' side.
    diameter_mm : float
    length_mm : float
        A slot's overall length (0: round).
    axis : (3,) tuple of float
        In-plane direction: a slot's long axis, and the hole's x (its y is
        ``normal x axis``).
    """

    centre: tuple[float, float, float]
    normal: tuple[float, float, float]
    diameter_mm: float
    length_mm: float = 0.0
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)


@dataclass(frozen=True)
class HoleMeasurement:
    """A hole measured in its own plane.

    Attributes
    ----------
    offset_mm : (2,) float64
        The measured centre minus the nominal one, along the hole's x and y (mm).
    diameter_mm, length_mm : float
        Measured (length: a slot's overall length; the diameter for a round hole).
    angle_deg : float
        The slot axis's turn from the nominal axis in the plane (0 for a round hole).
    sigma_mm : (4,) float64
        1 sigma of x, y, diameter and length.
    support : int
        Edge points the fit used.
    rms_mm : float
        Their residual from the fitted outline.
    cameras : int
        Cameras that contributed edge points.
    """

    offset_mm: npt.NDArray[np.float64]
    diameter_mm: float
    length_mm: float
    angle_deg: float
    sigma_mm: npt.NDArray[np.float64]
    support: int
    rms_mm: float
    cameras: int


@dataclass(frozen=True)
class TrimMeasurement:
    """A trim edge's offset normal to the edge, in the surface's tangent plane.

    Attributes
    ----------
    deviation_mm : float
        The curve fitted to the edge points: its mean offset over the measured
        span. Positive: the material reaches farther than drawn (along the
        edge's outward normal).
    sigma_mm : float
        1 sigma of the mean.
    spread_mm : float
        Robust scatter of the single edge points' offsets.
    support : int
        Edge points the curve was fitted to.
    cameras : int
    max_mm : float
        The fitted curve's signed offset of largest magnitude along the span.
    at : (3,) tuple of float, mm, CAD frame
        Where on the nominal edge it lies.
    robust_mm : float
        The single robust average of the points' offsets (no curve).
    curve : EdgeCurve
    """

    deviation_mm: float
    sigma_mm: float
    spread_mm: float
    support: int
    cameras: int
    max_mm: float
    at: tuple[float, float, float]
    robust_mm: float
    curve: EdgeCurve


def hole_frame(
    normal: npt.ArrayLike, axis: npt.ArrayLike
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """The hole's in-plane x (``axis`` made normal to ``normal``), y and its unit normal.

    Raises
    ------
    InvalidInput
        ``axis`` along ``normal``.
    """
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    a = np.asarray(axis, dtype=np.float64)
    x = a - (a @ n) * n
    if np.linalg.norm(x) < 1e-6:
        raise InvalidInput("a hole's axis must not lie along its normal")
    x /= np.linalg.norm(x)
    return x, np.cross(n, x), n


def rim_points(hole: HoleSpec, spacing_mm: float) -> tuple[Points, Points]:
    """Samples of a hole's nominal rim and their in-plane normals pointing into the material.

    Returns
    -------
    points : (K, 3) float64, mm, CAD frame
    outward : (K, 3) float64
        Unit, in the hole's plane, from the hole into the material.
    """
    x, y, _ = hole_frame(hole.normal, hole.axis)
    r = hole.diameter_mm / 2
    a = max(hole.length_mm / 2 - r, 0.0)
    uv, nv = _stadium(a, r, spacing_mm)
    c = np.asarray(hole.centre, dtype=np.float64)
    pts = c + uv[:, :1] * x + uv[:, 1:] * y
    out = nv[:, :1] * x + nv[:, 1:] * y
    return pts, out


def _stadium(a: float, r: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points and outward normals of a slot's outline in its own plane: half circles of
    radius ``r`` at (+-a, 0) joined by straight sides."""
    k = max(int(math.ceil(math.pi * r / spacing)), 8)
    th = np.linspace(-math.pi / 2, math.pi / 2, k, endpoint=False)
    right = np.column_stack([np.cos(th), np.sin(th)])
    parts_p = [right * r + [a, 0.0], -right * r + [-a, 0.0]]
    parts_n = [right, -right]
    if a > 0:
        m = max(int(math.ceil(2 * a / spacing)), 1)
        s = np.linspace(-a, a, m, endpoint=False) + a / m
        parts_p += [np.column_stack([s, np.full(m, r)]), np.column_stack([s, np.full(m, -r)])]
        parts_n += [np.tile([0.0, 1.0], (m, 1)), np.tile([0.0, -1.0], (m, 1))]
    return np.concatenate(parts_p), np.concatenate(parts_n)


def boundary_samples(
    vertices: Points,
    faces: npt.NDArray[np.int64],
    face_normals: Points,
    position: npt.ArrayLike,
    radius_mm: float,
    spacing_mm: float,
) -> tuple[Points, Points, Points]:
    """Samples of the CAD's boundary (edges of one face) within ``radius_mm`` of ``position``.

    Returns
    -------
    points : (K, 3) float64, mm
    outward : (K, 3) float64
        In the face's plane, normal to the edge, away from the face (out of the material).
    normals : (K, 3) float64
        The face's normal.
    """
    f = np.asarray(faces)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    owner = np.tile(np.arange(len(f)), 3)
    n_v = len(vertices)
    key = np.minimum(e[:, 0], e[:, 1]) * n_v + np.maximum(e[:, 0], e[:, 1])
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    single = counts[inv] == 1
    a, b = vertices[e[single, 0]], vertices[e[single, 1]]
    fn = face_normals[owner[single]]
    p = np.asarray(position, dtype=np.float64)
    near = (np.linalg.norm(a - p, axis=1) <= radius_mm + 1e-9) | (
        np.linalg.norm(b - p, axis=1) <= radius_mm + 1e-9
    )
    pts, outs, nrms = [], [], []
    tri = vertices[f]
    centroid = tri.mean(axis=1)[owner[single]]
    for a_i, b_i, n_i, c_i in zip(a[near], b[near], fn[near], centroid[near], strict=True):
        d = b_i - a_i
        length = float(np.linalg.norm(d))
        m = max(int(math.ceil(length / spacing_mm)), 1)
        s = (np.arange(m) + 0.5) / m
        q = a_i + s[:, None] * d
        keep = np.linalg.norm(q - p, axis=1) <= radius_mm
        out = np.cross(d / length, n_i)
        if out @ (a_i - c_i) < 0:
            out = -out
        out /= np.linalg.norm(out)
        pts.append(q[keep])
        outs.append(np.tile(out, (int(keep.sum()), 1)))
        nrms.append(np.tile(n_i, (int(keep.sum()), 1)))
    if not pts:
        empty = np.empty((0, 3))
        return empty, empty, empty
    return np.concatenate(pts), np.concatenate(outs), np.concatenate(nrms)


def edge_points(
    cameras: Sequence[Camera],
    images: Sequence[Image],
    T_cad_rig: Transform,
    samples: Points,
    into_material: Points,
    normals: Points,
    surface_offset_mm: float = 0.0,
    params: EdgeParams | None = None,
    flash: Flash | None = None,
) -> tuple[Points, npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The outline found in the images near its nominal samples (steps 2 and 3 above).

    Parameters
    ----------
    cameras, images : the calibrated cameras and their frames, in the same order
    T_cad_rig : (4, 4) float64
        The fit's pose.
    samples : (K, 3) float64, mm, CAD frame
        Nominal outline points.
    into_material : (K, 3) float64
        In-plane unit directions from the air into the material.
    normals : (K, 3) float64
        Surface normals at the samples (towards the cameras).
    surface_offset_mm : float
        The measured surface's offset from the CAD along the normal there.
    flash : Flash, optional
        The flash's slide; without it the material's light is taken as
        unpatterned (even lighting).

    Returns
    -------
    points : (M, 3) float64, mm, CAD frame
        Edge points on the (offset) tangent planes of their samples.
    sample : (M,) int64
        The sample each belongs to.
    camera : (M,) int64
        The camera that saw it.
    """
    p = params if params is not None else EdgeParams()
    T_rig_cad = np.linalg.inv(T_cad_rig).astype(np.float64)
    R = T_rig_cad[:3, :3]
    q_rig = apply(T_rig_cad, samples + surface_offset_mm * normals)
    e_rig = into_material @ R.T
    n_rig = normals @ R.T
    curvature = _outline_curvature(samples, into_material, normals)
    t = np.arange(-p.window_px, p.window_px + 1e-9, _PROFILE_STEP_PX)
    model = _edge_model_grid(p)
    pts_out, idx_out, cam_out = [], [], []
    for ci, (cam, img) in enumerate(zip(cameras, images, strict=True)):
        view = cam.centre - q_rig
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        seen = np.einsum("ij,ij->i", view, n_rig) >= p.min_cos
        if not seen.any():
            continue
        k = np.flatnonzero(seen)
        uv0 = cam.project(q_rig[k])
        uv1 = cam.project(q_rig[k] + 0.5 * e_rig[k])
        g = uv1 - uv0
        g_len = np.linalg.norm(g, axis=1)
        ok = np.isfinite(uv0).all(axis=1) & (g_len > 1e-6)
        h, w = img.shape
        margin = p.window_px + 2
        ok &= (uv0[:, 0] > margin) & (uv0[:, 0] < w - 1 - margin)
        ok &= (uv0[:, 1] > margin) & (uv0[:, 1] < h - 1 - margin)
        k, uv0, mm_per_px, g = k[ok], uv0[ok], 0.5 / g_len[ok], g[ok] / g_len[ok, None]
        if len(k) == 0:
            continue
        where = uv0[:, None, :] + t[None, :, None] * g[:, None, :]
        prof = cv2.remap(
            img.astype(np.float32),
            where[..., 0].astype(np.float32),
            where[..., 1].astype(np.float32),
            cv2.INTER_LINEAR,
        )
        slide = None
        if flash is not None:
            slide = flash.along(cam, uv0, g, model, q_rig[k], n_rig[k]).astype(np.float64)
        edge_t, sigma, good = _fit_edges(prof, t, slide, model, p)
        if not good.any():
            continue
        # A blurred outline's best-fitting step lies off the outline towards the side the
        # outline bends around, by half the blur's variance times the curvature.
        edge_t = edge_t + 0.5 * sigma**2 * curvature[k] * mm_per_px
        uv = uv0[good] + edge_t[good, None] * g[good]
        origin, direction = cam.rays(uv)
        kk = k[good]
        # The ray meets the tangent plane through its (offset) sample.
        denom = np.einsum("ij,ij->i", direction, n_rig[kk])
        lam = np.einsum("ij,ij->i", q_rig[kk] - origin, n_rig[kk]) / denom
        hit = origin + lam[:, None] * direction
        pts_out.append(apply(T_cad_rig, hit))
        idx_out.append(kk)
        cam_out.append(np.full(len(kk), ci))
    if not pts_out:
        return np.empty((0, 3)), np.empty(0, np.int64), np.empty(0, np.int64)
    return np.concatenate(pts_out), np.concatenate(idx_out), np.concatenate(cam_out)


def _edge_model_grid(p: EdgeParams) -> npt.NDArray[np.float64]:
    """Where the edge model is evaluated along a profile (pixels): the window and the
    blur's reach beyond it."""
    reach = p.window_px + 3.0 * max(p.blur_px)
    return np.arange(-reach, reach + 1e-9, _MODEL_STEP_PX)


def _outline_curvature(samples: Points, into_material: Points, normals: Points) -> Scalars:
    """Per sample, the outline's curvature in its surface plane (1/mm): positive where it
    bends around the air (a hole's rim: 1/radius), negative around the material, from a
    parabola through the samples within :data:`_CURVATURE_REACH_MM`."""
    tangent = np.cross(normals, into_material)
    out = np.zeros(len(samples))
    d = samples[None, :, :] - samples[:, None, :]
    near = np.linalg.norm(d, axis=2) <= _CURVATURE_REACH_MM
    for i in range(len(samples)):
        m = near[i]
        if m.sum() < 5:
            continue
        s = d[i, m] @ tangent[i]
        across = d[i, m] @ into_material[i]
        A = np.column_stack([np.ones_like(s), s, s * s])
        coef, *_ = np.linalg.lstsq(A, across, rcond=None)
        # Along the material's direction the outline falls away as -kappa s^2 / 2.
        out[i] = -2.0 * coef[2]
    return out


def _fit_edges(
    prof: np.ndarray, t: np.ndarray, slide: np.ndarray | None, model: np.ndarray, p: EdgeParams
) -> tuple[np.ndarray, float, np.ndarray]:
    """Per profile (rows over ``t``, from the air into the material): the edge, the
    camera's blur (one for all rows, pixels) and whether the edge is a clear one.

    The model of a profile is ``c + K * (a (. - t0) (1 - H(. - t0)) + (h + g s)
    H(. - t0))``, blurred by a Gaussian ``K`` across the edge: the air's level ``c``,
    and before the edge ``t0`` its slope ``a`` (the belt seen through a hole may lie
    in the penumbra of the flash's patch through it); from the edge on the material's
    light over the air's, unpatterned (``h``: stray light, the metal's sheen) and the
    slide ``s`` (``slide``, on the grid ``model``; without it, ``h`` alone). Every
    candidate ``t0`` (the model's grid within ``search_px``) is fitted over the same
    window, the levels by linear least squares, and the best one refined by a parabola
    through its neighbours' costs; the blur is the one of ``p.blur_px`` whose profiles
    fit best on the median.
    """
    from scipy.special import ndtr

    scan = np.flatnonzero(np.abs(model) <= p.search_px + 1e-9)
    prof = np.asarray(prof, dtype=np.float64)
    rows = np.arange(len(prof))
    best: tuple[float, float, np.ndarray, _EdgeSystem, np.ndarray] | None = None
    for sigma in p.blur_px:
        # The blur of a step at each model place, seen at each t: the columns' building
        # block, K(t - tau) summed over tau beyond the step.
        kern = ndtr((model[None, :] + 0.5 * _MODEL_STEP_PX - t[:, None]) / sigma) - ndtr(
            (model[None, :] - 0.5 * _MODEL_STEP_PX - t[:, None]) / sigma
        )  # (T, M): the share of model cell m in the blur at t
        system = _edge_normal_equations(prof, kern, model, scan, slide)
        # The least-squares fit's residual: |y|^2 - B . A^-1 B.
        sse = (prof * prof).sum(axis=1)[:, None] - system.explained()
        k = np.argmin(sse, axis=1)
        total = float(np.median(sse[rows, k]))
        if best is None or total < best[0]:
            best = (total, sigma, sse, system, k)
    assert best is not None
    _, sigma, sse, system, k = best
    coef = system.solve(k)
    kc = np.clip(k, 1, len(scan) - 2)
    y0, y1, y2 = sse[rows, kc - 1], sse[rows, kc], sse[rows, kc + 1]
    den = y0 - 2 * y1 + y2
    frac = np.where(den > 1e-12, 0.5 * (y0 - y2) / np.where(den > 1e-12, den, 1.0), 0.0)
    # Candidate j puts the edge between model cells j - 1 and j.
    te = model[scan][kc] - 0.5 * _MODEL_STEP_PX + np.clip(frac, -0.5, 0.5) * _MODEL_STEP_PX
    c = coef[:, 0]
    step = coef[:, 2]
    if slide is not None:
        at = np.clip(np.searchsorted(model, te), 0, len(model) - 1)
        step = step + coef[:, 3] * slide[rows, at]
    inside = (k > 0) & (k < len(scan) - 1)
    window = np.abs(t) <= p.window_px + 1e-9
    ok = inside & (step >= p.min_step_dn) & ~(prof[:, window] >= _SATURATED_DN).any(axis=1)
    # The air is the belt in the part's shadow; where the flash reaches the belt through
    # the hole beside the rim, the step found is the lit patch's, not the rim's.
    if ok.any():
        ok &= c - np.median(c[ok]) <= _AIR_FRACTION * step
    return te, sigma, ok


# Added to the normal matrices' diagonals: keeps a candidate whose columns nearly
# coincide (an edge at the window's end) solvable.
_EDGE_RIDGE = 1e-9


@dataclass(frozen=True)
class _EdgeSystem:
    """The normal equations ``A coef = B`` of :func:`_fit_edges`'s model, for n profiles
    at S candidate edges: ``A = [[shared, cross], [cross^T, own]]``, whose block of the
    three columns every profile has in common (the air's level and slope, the
    unpatterned light) is the same for all profiles; ``cross`` (n, S, 3) and ``own``
    (n, S), of the slide's column, are None without a slide; ``rhs`` (n, S, 3 or 4)."""

    shared: np.ndarray  # (S, 3, 3)
    cross: np.ndarray | None
    own: np.ndarray | None
    rhs: np.ndarray

    def explained(self) -> np.ndarray:
        """``B . A^-1 B`` per profile and candidate (n, S): the share of a profile's
        square sum that the candidate's least-squares fit explains. With the slide,
        through the Schur complement of the shared block, inverted once per candidate."""
        inv = np.linalg.inv(self.shared + _EDGE_RIDGE * np.eye(3))
        b0 = self.rhs[..., :3]
        q = np.einsum("nsi,nsi->ns", b0, np.einsum("sij,nsj->nsi", inv, b0))
        if self.cross is None or self.own is None:
            return q
        u = np.einsum("sij,nsj->nsi", inv, self.cross)  # shared^-1 cross
        schur = self.own + _EDGE_RIDGE - np.einsum("nsi,nsi->ns", self.cross, u)
        r = self.rhs[..., 3] - np.einsum("nsi,nsi->ns", u, b0)
        return q + r * r / schur

    def solve(self, k: np.ndarray) -> np.ndarray:
        """Each profile's coefficients at its candidate ``k`` (n,): (n, 3 or 4)."""
        rows = np.arange(len(k))
        b = self.rhs[rows, k]
        n, npar = b.shape
        A = np.empty((n, npar, npar))
        A[:, :3, :3] = self.shared[k]
        if self.cross is not None and self.own is not None:
            A[:, :3, 3] = A[:, 3, :3] = self.cross[rows, k]
            A[:, 3, 3] = self.own[rows, k]
        A += _EDGE_RIDGE * np.eye(npar)
        return np.asarray(np.linalg.solve(A, b[..., None])[..., 0])


def _edge_normal_equations(
    prof: np.ndarray,
    kern: np.ndarray,
    model: np.ndarray,
    scan: np.ndarray,
    slide: np.ndarray | None,
) -> _EdgeSystem:
    """The normal equations of :func:`_fit_edges`'s model for every profile (rows of
    ``prof`` over ``t``) at every candidate edge (the model cells ``scan``, a run of
    consecutive ones), for a blur whose shares of the model cells at each ``t`` are
    ``kern`` (T, M).

    The columns over ``t`` of a candidate at cell ``c``: 1 (the air's level); the
    air's slope (the belt's light through a hole need not be even), the blur of
    ``(tau - model[c])`` over the cells before ``c``; the
    material's unpatterned light, the blur of the cells from ``c`` on; and with the
    slide, the blur of the slide over those cells, one column per profile. That last
    one would make an (n, T, S) array; its sums are taken over the model cells
    instead, where they are products with the blur's own Gram matrix and sums over
    the cells from ``c`` on.
    """

    def from_each_candidate(x: np.ndarray) -> np.ndarray:
        """Sums of ``x`` (rows over the model cells) over the cells from each
        candidate's on: (rows, S)."""
        return np.cumsum(x[:, ::-1], axis=1)[:, ::-1][:, scan]

    plain = from_each_candidate(kern)  # (T, S)
    before = np.cumsum(kern, axis=1) - kern  # the cells before each one
    moment = np.cumsum(kern * model[None, :], axis=1) - kern * model[None, :]
    cols = [
        np.ones_like(plain),
        moment[:, scan] - model[scan][None, :] * before[:, scan],
        plain,
    ]
    n, S = len(prof), len(scan)
    shared = np.empty((S, 3, 3))
    rhs = np.empty((n, S, 3 if slide is None else 4))
    for i, ci in enumerate(cols):
        rhs[..., i] = prof @ ci
        for j in range(i, 3):
            shared[:, i, j] = shared[:, j, i] = (ci * cols[j]).sum(axis=0)
    if slide is None:
        return _EdgeSystem(shared, None, None, rhs)
    # The slide's column is lit[n, t, c] = sum over m >= c of kern[t, m] slide[n, m].
    later = np.arange(kern.shape[1])[None, :] >= scan[:, None]  # (S, M)
    cross = np.stack([slide @ np.where(later, ci.T @ kern, 0.0).T for ci in cols], axis=2)
    rhs[..., 3] = from_each_candidate(slide * (prof @ kern))
    # sum_t lit^2 = sum over m, m' >= c of slide_m slide_m' G[m, m'], G = kern^T kern:
    # each cell adds its diagonal term and twice its products with the later cells.
    gram = kern.T @ kern
    later_products = slide @ np.triu(gram, 1).T
    own = from_each_candidate(slide * (slide * np.diag(gram) + 2.0 * later_products))
    return _EdgeSystem(shared, cross, own, rhs)


def measure_hole(
    hole: HoleSpec,
    cameras: Sequence[Camera],
    images: Sequence[Image],
    T_cad_rig: Transform,
    *,
    surface_offset_mm: float = 0.0,
    params: EdgeParams | None = None,
    min_support: int = 20,
    flash: Flash | None = None,
) -> tuple[HoleMeasurement | None, str | None]:
    """A hole's centre, diameter (and a slot's length and turn) from its rim in the images
    (``flash``: see :func:`edge_points`).

    Returns
    -------
    measurement : HoleMeasurement or None
    reason : str or None
        Why there is no measurement (no camera sees the rim, too few edge points).
    """
    p = params if params is not None else EdgeParams()
    samples, outward = rim_points(hole, p.sample_mm)
    normals = np.tile(np.asarray(hole.normal, dtype=np.float64) / np.linalg.norm(hole.normal),
                      (len(samples), 1))  # fmt: skip
    pts, _, cam = edge_points(
        cameras, images, T_cad_rig, samples, outward, normals, surface_offset_mm, p, flash
    )
    if len(pts) < min_support:
        if len(pts) == 0 and not _any_camera_faces(cameras, T_cad_rig, samples, normals, p):
            return None, "no camera sees its rim"
        return None, f"{len(pts)} rim points found in the images, {min_support} needed"
    x, y, _ = hole_frame(hole.normal, hole.axis)
    rel = pts - np.asarray(hole.centre, dtype=np.float64)
    uv = np.column_stack([rel @ x, rel @ y])
    return _fit_slot(uv, hole, cam, p, min_support)


def _any_camera_faces(cameras, T_cad_rig, samples, normals, p: EdgeParams) -> bool:
    T_rig_cad = np.linalg.inv(T_cad_rig)
    q = apply(T_rig_cad, samples)
    n = normals @ T_rig_cad[:3, :3].T
    for cam in cameras:
        v = cam.centre - q
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        if (np.einsum("ij,ij->i", v, n) >= p.min_cos).any():
            return True
    return False


def _slot_residuals(params: np.ndarray, uv: np.ndarray, slot: bool) -> np.ndarray:
    """Signed distance of each point from a slot's outline (positive outside the hole's
    air: in the material): distance to its axis segment minus the radius."""
    cx, cy, r = params[:3]
    a, phi = (params[3], params[4]) if slot else (0.0, 0.0)
    c, s = math.cos(phi), math.sin(phi)
    dx, dy = uv[:, 0] - cx, uv[:, 1] - cy
    along = c * dx + s * dy
    across = -s * dx + c * dy
    along = along - np.clip(along, -abs(a), abs(a))
    return np.hypot(along, across) - r


def _fit_slot(
    uv: np.ndarray, hole: HoleSpec, cam: np.ndarray, p: EdgeParams, min_support: int
) -> tuple[HoleMeasurement | None, str | None]:
    r0 = hole.diameter_mm / 2
    slot = hole.length_mm > hole.diameter_mm
    x0 = [0.0, 0.0, r0] + ([hole.length_mm / 2 - r0, 0.0] if slot else [])
    keep = np.ones(len(uv), bool)
    sol = None
    for _ in range(3):
        sol = least_squares(_slot_residuals, x0, args=(uv[keep], slot), loss="soft_l1", f_scale=0.1)
        res = _slot_residuals(sol.x, uv, slot)
        med = float(np.median(res[keep]))
        scale = 1.4826 * float(np.median(np.abs(res[keep] - med)))
        new = np.abs(res - med) <= p.reject_sigma * max(scale, 1e-3)
        x0 = sol.x
        if (new == keep).all():
            break
        keep = new
        if keep.sum() < min_support:
            return (
                None,
                f"{int(keep.sum())} rim points agree with one outline, {min_support} needed",
            )
    assert sol is not None
    res = _slot_residuals(sol.x, uv[keep], slot)
    n = int(keep.sum())
    dof = max(n - len(sol.x), 1)
    s2 = float(res @ res) / dof
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = np.full((len(sol.x), len(sol.x)), np.inf)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    cx, cy, r = sol.x[:3]
    if slot:
        a, phi = abs(float(sol.x[3])), float(sol.x[4])
        length = 2 * (a + r)
        sig = np.array([sd[0], sd[1], 2 * sd[2], 2 * math.hypot(sd[2], sd[3])])
    else:
        a, phi, length = 0.0, 0.0, 2 * r
        sig = np.array([sd[0], sd[1], 2 * sd[2], 2 * sd[2]])
    return (
        HoleMeasurement(
            offset_mm=np.array([cx, cy]),
            diameter_mm=float(2 * r),
            length_mm=float(length),
            angle_deg=math.degrees(phi),
            sigma_mm=sig,
            support=n,
            rms_mm=float(np.sqrt(np.mean(res * res))),
            cameras=int(len(np.unique(cam[keep]))),
        ),
        None,
    )


def measure_trim_edge(
    samples: Points,
    outward: Points,
    normals: Points,
    cameras: Sequence[Camera],
    images: Sequence[Image],
    T_cad_rig: Transform,
    *,
    surface_offset_mm: float = 0.0,
    params: EdgeParams | None = None,
    min_support: int = 10,
    curve: CurveParams | None = None,
    flash: Flash | None = None,
) -> tuple[TrimMeasurement | None, str | None]:
    """A trim edge's offset along its outward normal, from its nominal ``samples``.

    The edge points found in the images are fitted by a curve against the
    nominal made from ``samples`` (:func:`inspection.edge_curve.curve_offset`);
    too few points, or a fit that does not converge, leave the edge unmeasured.

    Parameters
    ----------
    samples : (K, 3) float64, mm, CAD frame
        The nominal edge near the point (:func:`boundary_samples`).
    outward : (K, 3) float64
        In-plane, normal to the edge, out of the material.
    normals : (K, 3) float64
        Surface normals.
    flash : Flash, optional
        See :func:`edge_points`.
    """
    p = params if params is not None else EdgeParams()
    if len(samples) == 0:
        return None, "no CAD edge near the point"
    pts, k, cam = edge_points(
        cameras, images, T_cad_rig, samples, -outward, normals, surface_offset_mm, p, flash
    )
    if len(pts) < min_support:
        if len(pts) == 0 and not _any_camera_faces(cameras, T_cad_rig, samples, normals, p):
            return None, "no camera sees the edge"
        return None, f"{len(pts)} edge points found in the images, {min_support} needed"
    off = np.einsum("ij,ij->i", pts - samples[k], outward[k])
    from .deviations import robust_location  # the comparison points' own estimator

    robust, spread = robust_location(off)
    try:
        nominal = nominal_curve(samples)
    except InvalidInput as exc:
        return None, f"the CAD's edge near the point gives no curve: {exc}"
    c = curve if curve is not None else CurveParams(reject_sigma=p.reject_sigma)
    fitted, why = curve_offset(pts, nominal, samples, outward, c, min_support=min_support)
    if fitted is None:
        return None, why
    return (
        TrimMeasurement(
            deviation_mm=fitted.offset_mm,
            sigma_mm=fitted.sigma_mm,
            spread_mm=spread,
            support=fitted.support,
            cameras=int(len(np.unique(cam))),
            max_mm=fitted.max_mm,
            at=fitted.at,
            robust_mm=robust,
            curve=fitted,
        ),
        None,
    )


def hole_from_cloud(
    hole: HoleSpec,
    points_cad: Points,
    *,
    band_mm: float = 6.0,
    max_height_mm: float = 1.0,
    bins: int = 72,
    min_support: int = 12,
) -> tuple[HoleMeasurement | None, str | None]:
    """A hole from the cloud alone: per angular sector about the nominal centre, the
    measured point nearest the rim's inside, fitted by a circle or slot.

    The cloud's rim lies inside the material by about half a matching window;
    this estimate carries that bias (the bench measures it).
    """
    x, y, n = hole_frame(hole.normal, hole.axis)
    rel = np.asarray(points_cad, dtype=np.float64) - np.asarray(hole.centre, dtype=np.float64)
    h = rel @ n
    uv = np.column_stack([rel @ x, rel @ y])
    r0 = hole.diameter_mm / 2
    a0 = max(hole.length_mm / 2 - r0, 0.0)
    along = uv[:, 0] - np.clip(uv[:, 0], -a0, a0)
    dist = np.hypot(along, uv[:, 1]) - r0
    near = (np.abs(h) <= max_height_mm) & (dist > -r0) & (dist < band_mm)
    if near.sum() < min_support:
        return None, f"{int(near.sum())} cloud points near the rim, {min_support} needed"
    ang = np.arctan2(uv[near, 1], uv[near, 0])
    sector = ((ang + math.pi) / (2 * math.pi) * bins).astype(np.int64) % bins
    d = dist[near]
    idx = np.flatnonzero(near)
    rim = []
    for s in range(bins):
        m = sector == s
        if m.any():
            rim.append(idx[m][np.argmin(d[m])])
    if len(rim) < min_support:
        return None, f"{len(rim)} sectors of the rim seen in the cloud, {min_support} needed"
    return _fit_slot(uv[rim], hole, np.zeros(len(rim), np.int64), EdgeParams(), min_support)

"""Holes, slots and trim edges measured on the part, after the fit, in the CAD frame.

A stereo cloud is blind at a part's outline: window matching loses the
points within about half a window of an edge, so a hole's rim taken from
the cloud comes out too large and a trim edge too short. The flash images
show the outline sharply, so the outline is measured in them:

1. the nominal outline (a hole's rim, or the CAD's boundary near a trim-edge
   point) is sampled in the CAD frame and carried into each camera that
   faces it by the fit's pose;
2. along each sample's in-plane normal, projected into the image, the grey
   profile is read at sub-pixel steps from the air (dark: the belt below a
   hole lies in the part's shadow) into the material, and the edge is placed
   where a blurred step, fitted to the profile, has its edge (the material's
   brightness may slope under it: the speckle); profiles without a clear
   step are dropped;
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

from .arrays import Image, Points, Transform
from .edge_curve import CurveParams, EdgeCurve, curve_offset, nominal_curve
from .errors import InvalidInput
from .rig import Camera
from .transforms import apply

log = logging.getLogger(__name__)

__all__ = [
    "EdgeParams",
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

# The profile is read every quarter pixel.
_PROFILE_STEP_PX = 0.25
# A profile whose air is brighter than the feature's darkest typical air by more than this
# fraction of its step does not see the rim against the shadowed belt.
_AIR_FRACTION = 0.2


@dataclass(frozen=True)
class EdgeParams:
    """How edges are searched in the images.

    Attributes
    ----------
    search_px : float
        The profile reaches this far on either side of the nominal outline
        (a hole shifted by up to about this many pixels is still found).
    min_step_dn : float
        A profile whose fitted step (the material's brightness at the edge over
        the air's) is smaller is dropped: where a dark speckle grain lies on the
        rim, the grain's own far edge competes with the rim and pulls the fit
        (against the simulator's truth, profiles with steps below about 60 DN
        came out a third to half a pixel off on the median, brighter ones within
        a tenth).
    sample_mm : float
        Spacing of the outline's samples.
    min_cos : float
        A camera sees a sample when the cosine between the surface normal and
        the direction to the camera is at least this.
    reject_sigma : float
        Edge points farther than this many robust sigmas from the fit are
        dropped, and the fit repeated.
    """

    search_px: float = 4.0
    min_step_dn: float = 50.0
    sample_mm: float = 0.5
    min_cos: float = 0.3
    reject_sigma: float = 3.0


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
    t = np.arange(-p.search_px, p.search_px + 1e-9, _PROFILE_STEP_PX)
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
        margin = p.search_px + 2
        ok &= (uv0[:, 0] > margin) & (uv0[:, 0] < w - 1 - margin)
        ok &= (uv0[:, 1] > margin) & (uv0[:, 1] < h - 1 - margin)
        k, uv0, g = k[ok], uv0[ok], (g[ok] / g_len[ok, None])
        if len(k) == 0:
            continue
        where = uv0[:, None, :] + t[None, :, None] * g[:, None, :]
        prof = cv2.remap(
            img.astype(np.float32),
            where[..., 0].astype(np.float32),
            where[..., 1].astype(np.float32),
            cv2.INTER_LINEAR,
        )
        edge_t, good = _step_fit(prof, t, p.min_step_dn)
        if not good.any():
            continue
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


_SIGMAS_PX = (0.5, 0.65, 0.8, 1.0, 1.25)
_T0_STEP_PX = 0.05
_FIT_HALF_PX = 2.0


def _step_fit(prof: np.ndarray, t: np.ndarray, min_step: float) -> tuple[np.ndarray, np.ndarray]:
    """Per profile (rows, from the dark air into the lit material): the edge of a blurred
    step fitted to it, and whether that is a clear step inside the search.

    The model over a window of +-2 px about the edge ``t0`` is
    ``c + (a + b (t - t0)) Phi((t - t0) / sigma)``: the air's level ``c``, the
    material's brightness ``a`` with its slope ``b`` (the speckle changes it
    within a few pixels), a Gaussian blur ``sigma``. For each candidate
    ``(t0, sigma)`` on a grid the three linear terms are solved in closed form;
    the best candidate's ``t0`` is refined by a parabola through its neighbours'
    costs.
    """
    from scipy.special import ndtr

    t0s = np.arange(t[0] + _FIT_HALF_PX, t[-1] - _FIT_HALF_PX + 1e-9, _T0_STEP_PX)
    n_rows = len(prof)
    best = np.full((n_rows, len(t0s)), np.inf)
    gain = np.zeros((n_rows, len(t0s)))
    air = np.zeros((n_rows, len(t0s)))
    for sigma in _SIGMAS_PX:
        for j, t0 in enumerate(t0s):
            m = np.abs(t - t0) <= _FIT_HALF_PX
            u = t[m] - t0
            phi = ndtr(u / sigma)
            B = np.column_stack([np.ones_like(u), phi, u * phi])
            coef, *_ = np.linalg.lstsq(B, prof[:, m].T, rcond=None)
            sse = ((prof[:, m] - (B @ coef).T) ** 2).sum(axis=1)
            better = sse < best[:, j]
            best[:, j] = np.where(better, sse, best[:, j])
            gain[:, j] = np.where(better, coef[1], gain[:, j])
            air[:, j] = np.where(better, coef[0], air[:, j])
    k = np.argmin(best, axis=1)
    rows = np.arange(n_rows)
    kc = np.clip(k, 1, len(t0s) - 2)
    y0, y1, y2 = best[rows, kc - 1], best[rows, kc], best[rows, kc + 1]
    den = y0 - 2 * y1 + y2
    frac = np.where(den > 1e-12, 0.5 * (y0 - y2) / np.where(den > 1e-12, den, 1.0), 0.0)
    te = t0s[kc] + np.clip(frac, -0.5, 0.5) * _T0_STEP_PX
    inside = (k > 0) & (k < len(t0s) - 1)
    ok = inside & (gain[rows, k] >= min_step)
    # The air is the belt in the part's shadow; where the flash reaches the belt through
    # the hole beside the rim, the step found is the lit patch's, not the rim's.
    c = air[rows, k]
    if ok.any():
        ok &= c - np.median(c[ok]) <= _AIR_FRACTION * gain[rows, k]
    return te, ok


def measure_hole(
    hole: HoleSpec,
    cameras: Sequence[Camera],
    images: Sequence[Image],
    T_cad_rig: Transform,
    *,
    surface_offset_mm: float = 0.0,
    params: EdgeParams | None = None,
    min_support: int = 20,
) -> tuple[HoleMeasurement | None, str | None]:
    """A hole's centre, diameter (and a slot's length and turn) from its rim in the images.

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
        cameras, images, T_cad_rig, samples, outward, normals, surface_offset_mm, p
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
    """
    p = params if params is not None else EdgeParams()
    if len(samples) == 0:
        return None, "no CAD edge near the point"
    pts, k, cam = edge_points(
        cameras, images, T_cad_rig, samples, -outward, normals, surface_offset_mm, p
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

"""Local photogrammetry at the comparison points: small warped windows around each point only.

Given the part's pose, each comparison point and its support disc are
projected into the rectified left view of every stereo pair whose two
cameras see the point's face. There, and only there:

1. the CAD at the pose is drawn into the patch (a rasteriser's facets, walked
   and ray cast as a :class:`~inspection.perspective.PerspectiveMap` is, by
   :func:`~inspection.perspective.surface_seen`): per pixel its point on the
   surface, hence the disparity the pair would measure if the part were its
   CAD;
2. the patch and the part of the right view those disparities reach are
   rectified from the frames (slices of the pair's rectification maps), and
   normalised as the cloud path normalises its crops;
3. a window at every ``stride``-th pixel whose CAD point lies within the
   support radius is fitted with the matching's warped kernel
   (:func:`~inspection.reconstruct.kernels.refine_warped`), its shape the
   CAD's disparity field: only each window's own disparity is measured, so
   a dent is not guided away; a window on a bend also fits the light that
   changes with the surface there, as the cloud path's guided windows do
   (:func:`~inspection.reconstruct.warping.shading`);
4. each accepted window's disparity places the surface on the pixel's ray;
   its offset from the CAD point, along the facet's normal, is the window's
   deviation;
5. the windows of every pair are pooled by the Tukey biweight (as the cloud
   path pools its points); the uncertainty is the pooled spread over the
   independent windows, and the calibration's disparity error through each
   pair's depth, in quadrature.

A point is not measurable when no pair sees it well, and the reason says
why for each pair (the angle to a camera, the image's edge, an occlusion, too
few windows that match).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from ..deviations import ComparisonPoint, robust_location
from ..errors import InvalidInput
from ..perspective import FacetSet, RayCaster, pinhole_faces, rectified_rays, surface_seen
from ..reconstruct import Reconstructor, ReconstructParams
from ..reconstruct.matching import local_normalise, spline_rows
from ..reconstruct.pairs import RectifiedPair, rectified_pair
from ..reconstruct.params import SATURATION_DN
from ..reconstruct.warping import refit_windows, shading
from ..rig import Rig
from ..transforms import apply
from ..validate import validate_transform
from .params import LocalParams

PATCH_MARGIN_MM = 20.0
"""Beyond a point's support, how far its patches reach on the part: the windows'
and normalisation's half widths (~13 px of ~0.8 mm) on a surface seen obliquely."""


@dataclass(frozen=True)
class PairLook:
    """What one pair gave at one comparison point.

    Attributes
    ----------
    pair : str
        ``"a-b"``, the cameras' indices.
    windows : int
        Windows fitted.
    accepted : int
        Windows that matched (score, convergence, shift).
    reason : str or None
        Why the pair gave nothing (None: it gave ``accepted`` windows).
    """

    pair: str
    windows: int = 0
    accepted: int = 0
    reason: str | None = None


@dataclass(frozen=True, eq=False)
class PointMeasurement:
    """One comparison point measured by local photogrammetry.

    Attributes
    ----------
    name : str
    deviation_mm : float
        Robust average of the windows' deviations along the CAD normal (NaN:
        not measurable).
    sigma_mm : float
        1-sigma uncertainty of ``deviation_mm`` from the matching and the
        calibration (NaN: not measurable).
    spread_mm : float
        Robust standard deviation of the windows' deviations.
    support : int
        Windows pooled.
    pairs : tuple of PairLook
        Per pair tried.
    reason : str or None
        Why the point is not measurable.
    points : (N, 3) float64, mm, rig frame
        The triangulated window centres.
    deviations : (N,) float64, mm
        Each window's deviation.
    """

    name: str
    deviation_mm: float
    sigma_mm: float
    spread_mm: float
    support: int
    pairs: tuple[PairLook, ...]
    reason: str | None = None
    points: npt.NDArray[np.float64] = field(default_factory=lambda: np.empty((0, 3)), repr=False)
    deviations: npt.NDArray[np.float64] = field(default_factory=lambda: np.empty(0), repr=False)

    @property
    def measurable(self) -> bool:
        return self.reason is None


@dataclass(frozen=True, eq=False)
class LocalModel:
    """What local photogrammetry needs of a part and a rig, built once.

    Attributes
    ----------
    caster : RayCaster
        The CAD's exact ray casting (CAD frame).
    points : tuple of ComparisonPoint
    pairs : tuple of RectifiedPair
        The rig's stereo pairs, ring pairs included.
    facets : tuple of FacetSet
        Per point, the facets near enough to be seen in its patches (the
        support and the windows' margin, :data:`PATCH_MARGIN_MM`).
    centres : (C, 4) float64, mm, rig frame
        The cameras' centres (homogeneous), whose view of each point is checked.
    shapes : tuple of (int, int)
        Each camera's image (height, width).
    """

    caster: RayCaster
    points: tuple[ComparisonPoint, ...]
    pairs: tuple[RectifiedPair, ...]
    facets: tuple[FacetSet, ...] = field(repr=False)
    centres: npt.NDArray[np.float64] = field(repr=False)
    shapes: tuple[tuple[int, int], ...] = ()

    @classmethod
    def build(
        cls,
        cad: object,
        points: Sequence[ComparisonPoint],
        rig: Rig | Reconstructor,
        *,
        ring_pairs: bool = True,
        caster: RayCaster | None = None,
    ) -> LocalModel:
        """The model of ``cad`` (CadModel or trimesh.Trimesh, CAD frame) with its comparison
        ``points``, seen by ``rig`` (a Reconstructor's rectified pairs are reused), through
        the rig's stereo pairs and, with ``ring_pairs``, its ring pairs; ``caster``: the
        CAD's ray casting when already built (it is the costly part)."""
        pts = tuple(points)
        if not all(isinstance(p, ComparisonPoint) for p in pts):
            raise InvalidInput("points must be ComparisonPoint")
        if isinstance(rig, Rig):
            with Reconstructor.build(rig, ReconstructParams(threads=1)) as rec:
                return cls.build(cad, pts, rec, ring_pairs=ring_pairs, caster=caster)
        if not isinstance(rig, Reconstructor):
            raise InvalidInput(f"rig must be a Rig or a Reconstructor, got {type(rig).__name__}")
        pairs = list(rig.pairs + (rig.guide_pairs if ring_pairs else ()))
        lo, hi, the_rig = rig.volume_lo, rig.volume_hi, rig.rig
        have = {frozenset((p.left, p.right)) for p in pairs}
        for a, b in the_rig.stereo_pairs + (the_rig.ring_pairs if ring_pairs else ()):
            if frozenset((a, b)) not in have:
                pairs.append(rectified_pair(the_rig, a, b, lo, hi))
        if caster is None:
            caster = RayCaster(cad)
        facets = tuple(
            FacetSet.of(caster, caster.near(cp.position, cp.radius_mm + PATCH_MARGIN_MM))
            for cp in pts
        )
        centres = np.array([[*c.centre, 1.0] for c in the_rig.cameras])
        shapes = tuple(c.shape for c in the_rig.cameras)
        return cls(caster, pts, tuple(pairs), facets, centres, shapes)


def measure_points(
    model: LocalModel,
    frames: Sequence[npt.NDArray[np.uint8]],
    T_cad_rig: npt.ArrayLike,
    params: LocalParams | None = None,
) -> tuple[PointMeasurement, ...]:
    """Measure every comparison point of ``model`` in ``frames`` with the part at a pose.

    Parameters
    ----------
    model : LocalModel
    frames : sequence of (H, W) uint8, one per camera
    T_cad_rig : (4, 4)
        The part's pose (rig -> CAD), e.g. a fit's ``transform``.
    params : LocalParams, optional

    Returns
    -------
    tuple of PointMeasurement
        One per comparison point, in order.
    """
    p = params if params is not None else LocalParams()
    T_cad = validate_transform(T_cad_rig, name="T_cad_rig")
    T_rig = np.asarray(np.linalg.inv(T_cad), dtype=np.float64)
    imgs = [np.asarray(f) for f in frames]
    if not all(f.ndim == 2 and f.dtype == np.uint8 for f in imgs):
        raise InvalidInput("frames must be (H, W) uint8 images")
    needed = len(model.shapes)
    wrong = [k for k, f in enumerate(imgs[:needed]) if f.shape != model.shapes[k]]
    if wrong:
        k = wrong[0]
        raise InvalidInput(f"frame {k} is {imgs[k].shape}, the rig's camera {k} gives "
                           f"{model.shapes[k]}")  # fmt: skip
    if len(imgs) != needed:
        raise InvalidInput(f"{len(imgs)} frames given, one per camera ({needed}) needed")
    # Resampled in float32, as the cloud path does, so that the windows see no second
    # quantisation; converted once per frame, not per patch.
    floats = [f.astype(np.float32) for f in imgs]
    return tuple(_measure_point(model, floats, T_rig, k, p) for k in range(len(model.points)))


def _measure_point(
    model: LocalModel,
    frames: list[npt.NDArray[np.float32]],
    T_rig: npt.NDArray[np.float64],
    k: int,
    p: LocalParams,
) -> PointMeasurement:
    cp, facets = model.points[k], model.facets[k]
    X = apply(T_rig, np.asarray([cp.position], dtype=np.float64))[0]
    n = T_rig[:3, :3] @ np.asarray(cp.normal, dtype=np.float64)
    looks: list[PairLook] = []
    devs: list[npt.NDArray[np.float64]] = []
    pts: list[npt.NDArray[np.float64]] = []
    cal_var: list[float] = []
    sees = _cameras_see(model, T_rig, X, p.occlusion_mm)
    for pair in model.pairs:
        look, d, x, var = _one_pair(model, frames, pair, T_rig, X, n, cp.radius_mm, facets, sees, p)
        looks.append(look)
        if look.reason is None:
            devs.append(d)
            pts.append(x)
            cal_var.append(var)
    if not devs:
        why = "; ".join(f"pair {k.pair}: {k.reason}" for k in looks)
        return PointMeasurement(cp.name, math.nan, math.nan, math.nan, 0, tuple(looks),
                                f"no camera pair sees it well ({why})")  # fmt: skip
    d_all = np.concatenate(devs)
    mu, spread = robust_location(d_all)
    # Overlapping windows share pixels: count independent ones by area.
    independent = max(len(d_all) * p.stride**2 / p.window**2, 1.0)
    sigma_match = spread / math.sqrt(independent)
    # The calibration's error is one per pair, not averaged down by windows.
    sigma_cal = math.sqrt(sum(cal_var)) / len(cal_var)
    sigma = math.hypot(sigma_match, sigma_cal)
    return PointMeasurement(cp.name, mu, sigma, spread, len(d_all), tuple(looks), None,
                            np.concatenate(pts), d_all)  # fmt: skip


def _one_pair(
    model: LocalModel,
    frames: list[npt.NDArray[np.float32]],
    pair: RectifiedPair,
    T_rig: npt.NDArray[np.float64],
    X: npt.NDArray[np.float64],
    n: npt.NDArray[np.float64],
    radius_mm: float,
    facets: FacetSet,
    sees: npt.NDArray[np.bool_],
    p: LocalParams,
) -> tuple[PairLook, npt.NDArray[np.float64], npt.NDArray[np.float64], float]:
    """The windows of one pair at one point: (look, deviations, points, calibration variance)."""
    empty = np.empty(0), np.empty((0, 3)), 0.0
    name = pair.name
    # Seen by both cameras, not at a grazing angle?
    centres = (pair.centre_left, pair.centre_left + pair.baseline_mm * pair.R_rect_rig[0])
    cos_max = math.cos(math.radians(p.max_view_deg))
    for cam, c in zip((pair.left, pair.right), centres, strict=True):
        v = c - X
        cos = float(n @ v) / float(np.linalg.norm(v))
        if cos < cos_max:
            angle = math.degrees(math.acos(max(min(cos, 1.0), -1.0)))
            return PairLook(name, reason=f"cam{cam} sees it at {angle:.0f} deg"), *empty
    xs, ys, zs = pair.project(X[None])
    xc, yc, z = float(xs[0]), float(ys[0]), float(zs[0])
    hw = p.window // 2
    # The normalisation's margin: the patch reaches it beyond the windows.
    m = p.norm_window // 2
    half = int(math.ceil(radius_mm * pair.f_px / z)) + hw + m + 1
    x0, y0 = int(round(xc)) - half, int(round(yc)) - half
    size = 2 * half + 1
    w_img, h_img = pair.size
    if x0 < 0 or y0 < 0 or x0 + size > w_img or y0 + size > h_img:
        return PairLook(name, reason="the support leaves the rectified view"), *empty
    for cam in (pair.left, pair.right):
        if not sees[cam]:
            return PairLook(name, reason=f"cam{cam} does not see it (occluded)"), *empty
    # The CAD is drawn only where the windows reach: the patch less the normalisation's
    # margin, which reads the images alone.
    inner = size - 2 * m
    o, d = rectified_rays(pair, (x0 + m, y0 + m), (inner, inner))
    hint = pinhole_faces(model.caster, T_rig, facets, pair.R_rect_rig, pair.centre_left,
                         pair.f_px, (pair.cx_left, pair.cy), (x0 + m, y0 + m),
                         (inner, inner))  # fmt: skip
    face, at, normals = surface_seen(model.caster, T_rig, o, d, hint)
    seen = face >= 0
    depth = np.full(len(face), np.nan)
    depth[seen] = (at[seen] - pair.centre_left) @ pair.R_rect_rig[2]
    disp = pair.fb / depth + pair.offset_px  # NaN off the part
    field_ = np.full((size, size), np.nan)
    field_[m : m + inner, m : m + inner] = disp.reshape(inner, inner)
    d_lo, d_hi = float(disp[seen].min()), float(disp[seen].max())
    # The right view's columns those disparities reach, with the windows' margins.
    pad = hw + m + 2 + int(math.ceil(p.max_shift_px))
    rx0 = max(int(math.floor(x0 - d_hi)) - pad, 0)
    rx1 = min(int(math.ceil(x0 + size - d_lo)) + pad, w_img)
    rows = slice(y0, y0 + size)
    left = _rectify(frames[pair.left], pair.maps_left, rows, slice(x0, x0 + size))
    right = _rectify(frames[pair.right], pair.maps_right, rows, slice(rx0, rx1))
    left_n = local_normalise(left, p.norm_window)
    right_n = spline_rows(local_normalise(right, p.norm_window))
    wl = (left < SATURATION_DN - 0.5).astype(np.float32)
    wr = (right < SATURATION_DN - 0.5).astype(np.float32)
    # The windows: every stride-th pixel (of the image) whose CAD point lies within the
    # support; indices of the drawn square.
    gx = np.arange((-(x0 + m)) % p.stride, inner, p.stride)
    gy = np.arange((-(y0 + m)) % p.stride, inner, p.stride)
    cand = (gy[:, None] * inner + gx[None, :]).ravel()
    off = at[cand] - X
    with np.errstate(invalid="ignore"):
        sel = cand[np.einsum("ij,ij->i", off, off) <= radius_mm * radius_mm]
    if len(sel) == 0:
        return PairLook(name, reason="no window inside the support"), *empty
    shift = float(rx0 - x0)
    shape = np.where(np.isfinite(field_), field_ + shift, 0.0).astype(np.float32)
    mask = np.isfinite(field_).astype(np.float32)
    px = (sel % inner + m).astype(np.int64)
    py = (sel // inner + m).astype(np.int64)
    d0 = (disp[sel] + shift).astype(np.float32)
    out_d = np.empty(len(sel), np.float32)
    score = np.empty(len(sel), np.float32)
    step = np.empty(len(sel), np.float32)
    # Windows on a bend also fit the sheen, as the cloud path's guided windows do.
    shade, bent = shading(field_, p.window, p.shading_bend)
    on_bend = bent[py, px]
    images = (left_n, right_n, wl, wr, shape, mask, px, py)
    fit = (d0, hw, p.iterations, out_d, score, step)
    refit_windows(*images, ~on_bend, *fit)
    refit_windows(*images, on_bend, *fit, shade)
    ok = (
        np.isfinite(out_d)
        & (score >= p.min_score)
        & (np.abs(step) <= p.converged_px)
        & (np.abs(out_d - d0) <= p.max_shift_px)
    )
    look = PairLook(name, len(sel), int(ok.sum()))
    if look.accepted < p.min_windows:
        why = f"{look.accepted} of {len(sel)} windows matched (at least {p.min_windows} needed)"
        return PairLook(name, len(sel), look.accepted, why), *empty
    idx = sel[ok]
    d_meas = out_d[ok].astype(np.float64) - shift
    z_meas = pair.fb / (d_meas - pair.offset_px)
    ray = d[idx]
    rz = ray @ pair.R_rect_rig[2]
    measured = pair.centre_left + (z_meas / rz)[:, None] * ray
    dev = np.einsum("ij,ij->i", measured - at[idx], normals[idx])
    # The calibration's disparity error moves the depth by z^2 / (f B) per pixel,
    # seen along the normal through the ray's angle to it.
    cos_n = float(np.mean(np.abs(np.einsum("ij,ij->i", ray, normals[idx]))))
    sigma_z = z * z / pair.fb * p.calibration_px
    return look, dev, measured, (sigma_z * cos_n / float(np.mean(rz))) ** 2


def _rectify(
    img: npt.NDArray[np.float32],
    maps: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]],
    rows: slice,
    cols: slice,
) -> npt.NDArray[np.float32]:
    """A rectangle of the rectified view (as :func:`~inspection.reconstruct.pairs.rectify`,
    from the maps' slices)."""
    mx = np.ascontiguousarray(maps[0][rows, cols])
    my = np.ascontiguousarray(maps[1][rows, cols])
    out = cv2.remap(img, mx, my, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT)  # fmt: skip
    return np.asarray(out, dtype=np.float32)


def _cameras_see(
    model: LocalModel, T_rig: npt.NDArray[np.float64], X: npt.NDArray[np.float64], tol_mm: float
) -> npt.NDArray[np.bool_]:
    """Per camera, whether its ray to the rig-frame point ``X`` meets the part there first
    (one ray cast for all cameras)."""
    T_cad = np.asarray(np.linalg.inv(T_rig), dtype=np.float64)
    o = model.centres @ T_cad[:3].T
    x_cad = apply(T_cad, X[None])[0]
    d = x_cad - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    face, hit = model.caster.cast(o, d)
    with np.errstate(invalid="ignore"):
        return (face >= 0) & (np.linalg.norm(hit - x_cad, axis=1) <= tol_mm)


__all__ = ["LocalModel", "PairLook", "PointMeasurement", "measure_points"]

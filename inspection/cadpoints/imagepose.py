"""The part's pose from the frames themselves, without a cloud: its outline, then local
photogrammetry at sites spread over it.

1. **The outline's moments** (:func:`outline_pose`): in each camera the part
   is the bright region over the darker belt (the frame at a quarter of its
   size, blurred past the speckle, split at Otsu's threshold, its largest
   region). Its pixels, cast onto the plane at the height of the part's
   upward faces in a resting pose, give the footprint's centroid and main
   axis; the resting pose's template gives the CAD's. They place the part
   up to the axis' sign (and a quarter turn for a footprint without a main
   axis): one candidate pose per sign.
2. **The outline fitted in every camera at once**: each candidate's CAD is
   drawn into the four views (a :class:`~inspection.perspective.PerspectiveMap`
   at a quarter size), its outline pixels keep their 3D points, and the
   pose's six parameters are fitted so that those points project onto the
   seen outline: Gauss-Newton on the distance to it (its distance
   transform), Tukey's IRLS weights, drawn again after each fit. Only the
   facets facing up in the resting pose are drawn (the flanges' walls are
   dark, outside the bright region), and only the turn about the vertical
   and the shift on the belt are fitted (the outline alone lets the part
   tilt); at a quarter size the views are pinholes without distortion.
3. **The sites** (:func:`refine_pose`): at sites spread over the CAD and facing
   the cameras, small windows are matched with the CAD at the pose shaping
   them (:func:`.local.measure_points`); their points are fitted to the CAD
   by the robust registration, and matched again from the new pose. An
   outline that is nearly symmetric leaves the turn open between two
   candidates: both are refined, and the smaller residual wins
   (:func:`image_pose`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np
import numpy.typing as npt

from ..deviations import ComparisonPoint
from ..errors import InvalidInput
from ..perspective import FacetSet, RayCaster, pinhole_faces
from ..registration import LOSSES, RegisterParams, Registration, register
from ..rig import Camera, Rig
from ..transforms import apply
from .local import LocalModel, measure_points
from .params import LocalParams

if TYPE_CHECKING:
    from ..measure import PartModel

_SCALE = 4  # the outline is found at a quarter of the frame's size
_BLUR_SIGMA_PX = 2.0  # at that size: wider than the speckle's grain
_TUKEY_C = float(LOSSES["tukey"][1])
_UP_COS = 0.5  # the facets drawn for the outline: facing up in the resting pose
_ON_BELT = [2, 3, 4]
# The sites take walls seen at a grazing angle too: they fix the part in the belt's plane.
_SITES = LocalParams(max_view_deg=80.0)  # the twist's rotation about z, translation along x and y


@dataclass(frozen=True)
class OutlineFit:
    """The pose the outline gives.

    Attributes
    ----------
    transform : (4, 4) float64
        T_cad_rig.
    candidates : tuple of (4, 4) float64
        Every candidate's fitted pose (T_cad_rig), best outline first.
    residual_px : float
        RMS distance of the weighted outline points from the seen outline,
        full-size pixels.
    runner_up_px : float
        The other candidate's (inf: none).
    points : int
        Outline points fitted, over all cameras.
    iterations : int
    """

    transform: npt.NDArray[np.float64] = field(repr=False)
    candidates: tuple[npt.NDArray[np.float64], ...] = field(repr=False)
    residual_px: float
    runner_up_px: float
    points: int
    iterations: int


@dataclass(frozen=True, eq=False)
class ImagePoseModel:
    """What the image-based pose needs of a part and a rig, built once.

    Attributes
    ----------
    part : PartModel
        Its alignment model gives the resting poses and their templates.
    rig : Rig
    caster : RayCaster
    all_facets : FacetSet
    sites : LocalModel
        Local photogrammetry at sites spread over the CAD (the stereo pairs).
    """

    part: PartModel
    rig: Rig
    caster: RayCaster
    all_facets: FacetSet
    sites: LocalModel

    @classmethod
    def build(
        cls, part: PartModel, rig: Rig, *, sites: int = 40, site_radius_mm: float = 6.0
    ) -> ImagePoseModel:
        """Choose ``sites`` sites over the CAD (farthest-point sampling of area-weighted facet
        centres) and prepare their matching with ``rig``."""
        if part.alignment is None:
            raise InvalidInput("the part needs an alignment model (its resting poses)")
        caster = part.caster if part.caster is not None else RayCaster(part.cad)
        tri = caster.triangles
        centre = tri.mean(axis=1)
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        rng = np.random.default_rng(0)
        cand = rng.choice(len(tri), size=min(4000, len(tri)), replace=False, p=area / area.sum())
        chosen = [int(cand[0])]
        d = np.linalg.norm(centre[cand] - centre[cand[0]], axis=1)
        for _ in range(min(sites, len(cand)) - 1):
            k = int(np.argmax(d))
            chosen.append(int(cand[k]))
            d = np.minimum(d, np.linalg.norm(centre[cand] - centre[cand[k]], axis=1))
        pts = [
            ComparisonPoint(
                f"site{i}", tuple(centre[f]), tuple(caster.normals[f]), -1.0, 1.0, site_radius_mm
            )  # fmt: skip
            for i, f in enumerate(chosen)
        ]
        local = LocalModel.build(part.cad, pts, rig, ring_pairs=False, caster=caster)
        return cls(part, rig, caster, FacetSet.of(caster, np.arange(len(tri))), local)


def outline_pose(
    model: ImagePoseModel, frames: Sequence[npt.NDArray[np.uint8]], *, rounds: int = 3
) -> OutlineFit:
    """The pose of the part from its outline in the frames (steps 1 and 2 of the notes).

    Raises
    ------
    InvalidInput
        No part region in the frames.
    """
    rig = model.rig
    masks = [_part_mask(f) for f in frames]
    if not any(m.any() for m in masks):
        raise InvalidInput("no part seen in the frames (no region brighter than the belt)")
    dts = [_outline_distance(m) for m in masks]
    small = [_quarter(c) for c in rig.cameras]
    assert model.part.alignment is not None
    fits: list[tuple[float, npt.NDArray[np.float64], int, int]] = []
    for rest in model.part.alignment.poses[:2]:
        height = float(rest.template[:, 2].mean())
        foot = np.concatenate([_on_plane(rig, k, m, height) for k, m in enumerate(masks)])
        if len(foot) < 10:
            continue
        c_obs, axis_obs, elong = _moments(foot)
        c_t = rest.template[:, :2].mean(axis=0)
        turns = (0.0, math.pi) if elong < 0.8 else (0.0, math.pi / 2, math.pi, 1.5 * math.pi)
        for turn in turns:
            yaw = axis_obs - rest.axis_rad + turn
            T = np.eye(4)
            c, s = math.cos(yaw), math.sin(yaw)
            T[:2, :2] = [[c, -s], [s, c]]
            T[:2, 3] = c_obs - T[:2, :2] @ c_t
            T_rig_cad = T @ rest.transform
            up = FacetSet.of(model.caster, np.flatnonzero(
                model.caster.normals @ rest.transform[2, :3] > _UP_COS))  # fmt: skip
            cost, n, it = math.inf, 0, 0
            for _ in range(rounds):
                T_rig_cad, cost, n, k = _fit_outline(model, up, small, dts, T_rig_cad)
                it += k
            fits.append((cost, T_rig_cad, n, it))
    if not fits:
        raise InvalidInput("the part's outline is too small to place it")
    fits.sort(key=lambda f: f[0])
    cost, T, n, it = fits[0]
    runner = fits[1][0] if len(fits) > 1 else math.inf
    cands = tuple(np.asarray(np.linalg.inv(f[1]), dtype=np.float64) for f in fits)
    return OutlineFit(cands[0], cands, cost * _SCALE, runner * _SCALE, n, it)


def image_pose(
    model: ImagePoseModel, frames: Sequence[npt.NDArray[np.uint8]], *, close: float = 1.1
) -> tuple[Registration, OutlineFit]:
    """The part's pose from the images alone: the outline's, refined by the sites.

    The outline of a part that is nearly symmetric in outline does not tell
    its turn from the opposite one; every candidate whose outline fits within
    ``close`` times the best's residual is refined, and the refinement with
    the smallest residual (mm) wins, converged or not: the turn the wrong way
    round fits with a residual several times larger, while whether a fit has
    settled within its rounds says little about which turn is right. The fit
    says whether it converged.

    Raises
    ------
    InvalidInput
        No part seen, or no candidate could be refined.
    """
    outline = outline_pose(model, frames)
    tried = outline.candidates[: 2 if outline.runner_up_px <= close * outline.residual_px else 1]
    best: Registration | None = None
    for T in tried:
        try:
            fit = refine_pose(model, frames, T)
        except InvalidInput:
            continue
        if np.isfinite(fit.rms_mm) and (best is None or fit.rms_mm < best.rms_mm):
            best = fit
    if best is None:
        raise InvalidInput("no pose from the images: the sites did not fit any outline pose")
    return best, outline


def refine_pose(
    model: ImagePoseModel,
    frames: Sequence[npt.NDArray[np.uint8]],
    T_cad_rig: npt.ArrayLike,
    *,
    rounds: int = 3,
    params: RegisterParams | None = None,
) -> Registration:
    """The pose refined by the sites' local photogrammetry (step 3 of the notes).

    Returns
    -------
    Registration
        The last fit (``transform`` is T_cad_rig; convergence, residuals and the
        pose's covariance as every fit reports them).

    Raises
    ------
    InvalidInput
        Too few sites measured to fit the pose.
    """
    T = np.asarray(T_cad_rig, dtype=np.float64)
    rp = params or RegisterParams(max_iterations=30, max_distance_mm=3.0, view_direction=None)
    rp = dataclasses.replace(rp, escape_deg=None)
    fit: Registration | None = None
    for _ in range(rounds):
        measured = measure_points(model.sites, frames, T, _SITES)
        pts = [m.points for m in measured if m.measurable]
        if len(pts) < 6:
            raise InvalidInput(f"only {len(pts)} sites measured: too few to fit the pose")
        fit = register(model.part.tree, np.concatenate(pts), rp, init=T, faces=model.part.faces)
        T = np.asarray(fit.transform, dtype=np.float64)
    assert fit is not None
    return fit


# --------------------------------------------------------------------------- outline


def _fit_outline(
    model: ImagePoseModel,
    facets: FacetSet,
    cams: list[Camera],
    dts: list[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]],
    T_rig_cad: npt.NDArray[np.float64],
    iterations: int = 8,
) -> tuple[npt.NDArray[np.float64], float, int, int]:
    """Draw the CAD into each (quarter-size) view at ``T_rig_cad``, keep its outline's 3D
    points, and fit the pose's twist so that they land on the seen outline."""
    X, owner = [], []
    for k, cam in enumerate(cams):
        pts = _drawn_outline(model, facets, cam, T_rig_cad)
        X.append(pts)
        owner.append(np.full(len(pts), k))
    P = np.concatenate(X)
    cam_of = np.concatenate(owner)
    if len(P) < 20:
        return T_rig_cad, math.inf, len(P), 0
    centre = P.mean(axis=0)
    T = T_rig_cad
    cost = math.inf
    it = 0
    w = np.ones(len(P))
    for it in range(1, iterations + 1):  # noqa: B007
        r, J = _residuals(cams, dts, cam_of, P, centre)
        scale = max(1.4826 * float(np.median(np.abs(r))), 0.5)
        u = r / (_TUKEY_C * scale)
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        cost = math.sqrt(float(np.sum(w * r * r) / max(np.sum(w), 1e-12)))
        # On the belt: the turn about the vertical and the shift along it (the resting
        # pose fixes the rest, and the outline alone tilts the part freely).
        Jb = J[:, _ON_BELT]
        A = (Jb * w[:, None]).T @ Jb + 1e-6 * np.eye(3)
        x = np.zeros(6)
        x[_ON_BELT] = np.linalg.solve(A, -(Jb * w[:, None]).T @ r)
        dT = _twist(x, centre)
        P = apply(dT, P)
        T = dT @ T
        if np.abs(x[:3]).max() < 1e-5 and np.abs(x[3:]).max() < 1e-3:
            break
    return T, cost, len(P), it


def _residuals(
    cams: list[Camera],
    dts: list[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]],
    cam_of: npt.NDArray[np.int64],
    P: npt.NDArray[np.float64],
    centre: npt.NDArray[np.float64],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Each outline point's distance to the seen outline (quarter-size px) and its
    derivative by the twist (rotation about ``centre``, rad; translation, mm)."""
    r = np.zeros(len(P))
    J = np.zeros((len(P), 6))
    for k, cam in enumerate(cams):
        sel = cam_of == k
        if not sel.any():
            continue
        X = P[sel]
        pc = X @ cam.R.T + cam.t
        z = pc[:, 2]
        f = cam.K[0, 0]
        u = f * pc[:, 0] / z + cam.K[0, 2]
        v = cam.K[1, 1] * pc[:, 1] / z + cam.K[1, 2]
        dist, gx, gy = dts[k]
        r[sel] = _bilinear(dist, u, v)
        du, dv = _bilinear(gx, u, v), _bilinear(gy, u, v)
        # d(u, v)/d(camera point), then by the twist: dX = w x (X - c) + t.
        jx = np.stack([f / z, np.zeros_like(z), -f * pc[:, 0] / z**2], axis=1)
        jy = np.stack([np.zeros_like(z), cam.K[1, 1] / z, -cam.K[1, 1] * pc[:, 1] / z**2], axis=1)
        g = (du[:, None] * jx + dv[:, None] * jy) @ cam.R  # d r / d X (rig)
        J[sel, :3] = np.cross(X - centre, g)
        J[sel, 3:] = g
    return r, J


def _twist(x: npt.NDArray[np.float64], centre: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    R, _ = cv2.Rodrigues(np.asarray(x[:3], dtype=np.float64))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre + x[3:]
    return T


def _drawn_outline(
    model: ImagePoseModel, facets: FacetSet, cam: Camera, T_rig_cad: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """The 3D points (rig frame) of the CAD's outline pixels in a quarter-size pinhole view."""
    h, w = cam.height, cam.width
    R = cam.R
    faces = pinhole_faces(model.caster, T_rig_cad, facets, R, cam.centre, cam.K[0, 0],
                          (cam.K[0, 2], cam.K[1, 2]), (0, 0), (h, w))  # fmt: skip
    seen = (faces >= 0).reshape(h, w)
    edge = seen & ~cv2.erode(seen.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    idx = np.flatnonzero(edge.ravel())
    if len(idx) == 0:
        return np.empty((0, 3))
    ys, xs = np.divmod(idx, w)
    rays = np.stack([(xs - cam.K[0, 2]) / cam.K[0, 0], (ys - cam.K[1, 2]) / cam.K[1, 1],
                     np.ones(len(xs))], axis=1) @ R  # fmt: skip
    # Each outline pixel's ray met by its facet's plane (CAD frame, then back).
    T_cad = np.linalg.inv(T_rig_cad)
    f = faces[idx]
    o = T_cad[:3, :3] @ cam.centre + T_cad[:3, 3]
    d = rays @ T_cad[:3, :3].T
    n = model.caster.normals[f]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (model.caster.offsets[f] - n @ o) / np.einsum("ij,ij->i", n, d)
    q = o + s[:, None] * d
    ok = np.isfinite(s) & (s > 0)
    return apply(T_rig_cad, q[ok])


def _quarter(cam: Camera) -> Camera:
    return cam.with_size(cam.width // _SCALE, cam.height // _SCALE)


def _part_mask(frame: npt.NDArray[np.uint8]) -> npt.NDArray[np.bool_]:
    """The part's region at a quarter size: blurred, Otsu's threshold, largest region."""
    h, w = frame.shape
    small = cv2.resize(frame, (w // _SCALE, h // _SCALE), interpolation=cv2.INTER_AREA)
    blur = cv2.GaussianBlur(small, (0, 0), _BLUR_SIGMA_PX)
    _, bw = cv2.threshold(blur, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bw.astype(np.uint8), connectivity=4)
    if n <= 1:
        return np.zeros(small.shape, bool)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return np.asarray(labels == k)


def _outline_distance(
    mask: npt.NDArray[np.bool_],
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Distance (px) to the mask's outline everywhere, and its two slopes."""
    m = mask.astype(np.uint8)
    edge = m - cv2.erode(m, np.ones((3, 3), np.uint8))
    dist = cv2.distanceTransform((1 - edge).astype(np.uint8), cv2.DIST_L2, 5).astype(np.float32)
    gx = np.asarray(cv2.Sobel(dist, cv2.CV_32F, 1, 0, ksize=3), np.float32) / np.float32(8.0)
    gy = np.asarray(cv2.Sobel(dist, cv2.CV_32F, 0, 1, ksize=3), np.float32) / np.float32(8.0)
    return dist, gx, gy


def _bilinear(img: npt.NDArray[np.float32], u: npt.NDArray[np.float64],
              v: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:  # fmt: skip
    h, w = img.shape
    u = np.clip(u, 0.0, w - 1.001)
    v = np.clip(v, 0.0, h - 1.001)
    x0 = u.astype(np.int64)
    y0 = v.astype(np.int64)
    a, b = u - x0, v - y0
    out: npt.NDArray[np.float64] = (
        img[y0, x0] * (1 - a) * (1 - b) + img[y0, x0 + 1] * a * (1 - b)
        + img[y0 + 1, x0] * (1 - a) * b + img[y0 + 1, x0 + 1] * a * b
    )  # fmt: skip
    return out


def _on_plane(
    rig: Rig, k: int, mask: npt.NDArray[np.bool_], z_mm: float
) -> npt.NDArray[np.float64]:
    """The mask's pixels of camera ``k`` cast onto the plane z = ``z_mm`` (x, y)."""
    if not mask.any():
        return np.empty((0, 2))
    ys, xs = np.nonzero(mask)
    px = np.stack([(xs + 0.5) * _SCALE - 0.5, (ys + 0.5) * _SCALE - 0.5], axis=1)
    o, d = rig.cameras[k].rays(px)
    s = (z_mm - o[:, 2]) / d[:, 2]
    return (o + s[:, None] * d)[:, :2]


def _moments(xy: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], float, float]:
    """Centroid, major axis angle in [0, pi) and minor over major variance."""
    c = xy.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((xy - c).T))
    return c, math.atan2(v[1, 1], v[0, 1]) % math.pi, float(w[0] / max(w[1], 1e-12))


__all__ = ["ImagePoseModel", "OutlineFit", "image_pose", "outline_pose", "refine_pose"]

"""A simple depth-camera rig: a complete, self-contained set of pipeline stages.

The line's real stages are the four-camera flash rig (``inspection.simulate``
and ``inspection.reconstruct``) and the CAD-tree registration
(``inspection.align``, ``inspection.deviations``). This module provides a
much simpler stand-in for each, so that the line, its recorder and replay can
run end to end (and be tested) on any machine, with or without those stages:

- :func:`render`: a top-down orthographic depth camera over the measurement
  volume, by ray casting the mesh; depth travels losslessly as two ``mono8``
  images (high and low byte of the height in units of :data:`Z_UNIT_MM`);
- :func:`reconstruct`: decodes the two images back into rig-frame points;
- :func:`build_tree`, :func:`align`, :func:`deviations`: a kd-tree over
  surface samples, a PCA-initialised point-to-plane ICP that tries the
  in-plane flips, and signed point-to-plane deviations.

Everything is deterministic (fixed subsampling strides, no random numbers), so
replaying a FrameSet reproduces its result bit for bit.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from inspection.cad import CadModel
from inspection.errors import InsufficientOverlap, InvalidInput, ReconstructionError

log = logging.getLogger(__name__)

Z_UNIT_MM = 0.005
"""Height quantum of the depth images (mm per count); 0 means no surface."""
PIXEL_MM = 2.0
"""Pixel pitch of the depth camera on the conveyor plane, mm."""
VOLUME_MM = (800.0, 500.0, 200.0)
"""Measurement volume (x along the conveyor, y across, z up), centred at the origin in x, y."""
TREE_FORMAT = "depthrig-kdtree-1"


@dataclass(frozen=True)
class DepthRig:
    """Geometry of the depth camera: pixel pitch and volume, both in mm."""

    pixel_mm: float = PIXEL_MM
    volume_mm: tuple[float, float, float] = VOLUME_MM

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the depth images: rows along y, columns along x."""
        return int(round(self.volume_mm[1] / self.pixel_mm)), int(
            round(self.volume_mm[0] / self.pixel_mm)
        )

    def pixel_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """x and y (mm, rig frame) of every pixel centre, each (rows, cols)."""
        rows, cols = self.shape
        x = (np.arange(cols) + 0.5) * self.pixel_mm - self.volume_mm[0] / 2
        y = (np.arange(rows) + 0.5) * self.pixel_mm - self.volume_mm[1] / 2
        return np.meshgrid(x, y)

    @property
    def calibration_id(self) -> str:
        return f"depthrig-{self.pixel_mm:g}mm-{self.volume_mm[0]:g}x{self.volume_mm[1]:g}"


@dataclass(frozen=True, eq=False)
class Cloud:
    """Points (N, 3) float64 mm in the rig frame, weights (N,), report dict."""

    points: np.ndarray
    weights: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)


def render(rig: DepthRig, mesh: trimesh.Trimesh, T_rig_part: np.ndarray) -> list[np.ndarray]:
    """Render the depth images of ``mesh`` posed by ``T_rig_part``.

    Returns
    -------
    list of two (rows, cols) uint8
        High and low byte of ``round(z / Z_UNIT_MM)``, z the topmost surface
        height in mm (rig frame); 0 where no surface is seen.
    """
    posed = mesh.copy()
    posed.apply_transform(np.asarray(T_rig_part, dtype=np.float64))
    x, y = rig.pixel_centres()
    origins = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, rig.volume_mm[2] + 100.0)])
    dirs = np.tile([0.0, 0.0, -1.0], (x.size, 1))
    locs, ray_idx, _ = posed.ray.intersects_location(origins, dirs, multiple_hits=True)
    z = np.zeros(x.size)
    if len(ray_idx):
        # The camera sees the topmost hit along each ray.
        np.maximum.at(z, ray_idx, np.clip(locs[:, 2], 0.0, None))
    counts = np.clip(np.round(z / Z_UNIT_MM), 0, 65535).astype(np.uint16)
    counts[(z > 0) & (counts == 0)] = 1
    counts = counts.reshape(rig.shape)
    return [(counts >> 8).astype(np.uint8), (counts & 0xFF).astype(np.uint8)]


def reconstruct(rig: DepthRig, frames: list[np.ndarray]) -> Cloud:
    """Turn two depth images back into rig-frame points.

    Raises
    ------
    ReconstructionError
        Not two images of the rig's shape.
    """
    if len(frames) != 2 or any(f.shape != rig.shape or f.dtype != np.uint8 for f in frames):
        raise ReconstructionError(
            f"the depth rig needs two {rig.shape} mono8 images, got "
            f"{[(f.shape, str(f.dtype)) for f in frames]}"
        )
    counts = frames[0].astype(np.uint32) << 8 | frames[1].astype(np.uint32)
    x, y = rig.pixel_centres()
    seen = counts > 0
    pts = np.column_stack([x[seen], y[seen], counts[seen] * Z_UNIT_MM]).astype(np.float64)
    report: dict[str, Any] = {"points": int(len(pts)), "pixels": int(counts.size)}
    if not len(pts):
        report["flags"] = ["empty"]
    return Cloud(pts, np.ones(len(pts)), report)


@dataclass(frozen=True, eq=False)
class SampleTree:
    """Surface samples of a CAD model with their normals, in a kd-tree (CAD frame, mm)."""

    points: np.ndarray
    normals: np.ndarray
    kdtree: cKDTree
    cad_hash: str
    hash: str


def build_tree(cad: CadModel, spacing_mm: float = 1.5) -> SampleTree:
    """Sample the CAD surface (vertices and face centres, plus subdivisions) into a kd-tree."""
    mesh = trimesh.Trimesh(cad.vertices, cad.faces, process=False)
    # Subdivide until edges are below the spacing, then take vertices and face centres.
    v, f = trimesh.remesh.subdivide_to_size(cad.vertices, cad.faces, max_edge=spacing_mm * 2)
    sub = trimesh.Trimesh(v, f, process=False)
    pts = np.vstack([sub.triangles_center])
    normals = sub.face_normals
    del mesh
    digest = hashlib.sha256(f"{cad.hash}:{spacing_mm:g}:{TREE_FORMAT}".encode()).hexdigest()
    return SampleTree(pts, normals, cKDTree(pts), cad.hash, digest)


@dataclass(frozen=True, eq=False)
class Registration:
    """T_cad_data (4, 4), rms_mm, inlier_fraction, iterations, converged, stop_reason."""

    transform: np.ndarray
    rms_mm: float
    inlier_fraction: float
    iterations: int
    converged: bool
    stop_reason: str


def _stride_subsample(points: np.ndarray, n: int) -> np.ndarray:
    if len(points) <= n:
        return points
    return points[np.linspace(0, len(points) - 1, n).astype(np.int64)]


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _icp(
    tree: SampleTree,
    pts: np.ndarray,
    T: np.ndarray,
    iters: int,
    max_dist: float,
    tol_mm: float = 1e-7,
) -> tuple[np.ndarray, float, float, int, bool]:
    """Point-to-plane ICP with a distance gate; returns T, rms, inlier fraction, iterations."""
    rms = np.inf
    frac = 0.0
    for it in range(1, iters + 1):
        q = pts @ T[:3, :3].T + T[:3, 3]
        d, idx = tree.kdtree.query(q)
        inl = d < max_dist
        frac = float(inl.mean())
        if inl.sum() < 6:
            return T, np.inf, frac, it, False
        p, n, t = q[inl], tree.normals[idx[inl]], tree.points[idx[inl]]
        r = np.einsum("ij,ij->i", p - t, n)
        new_rms = float(np.sqrt(np.mean(r**2)))
        # Linearised point-to-plane step: [p x n, n] [w; v] = -r.
        A = np.column_stack([np.cross(p, n), n])
        x, *_ = np.linalg.lstsq(A, -r, rcond=None)
        w, v = x[:3], x[3:]
        theta = float(np.linalg.norm(w))
        if theta > 0:
            k = w / theta
            K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
            R = np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K
        else:
            R = np.eye(3)
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = R, v
        T = step @ T
        converged = abs(rms - new_rms) < tol_mm or (theta < 1e-9 and np.linalg.norm(v) < 1e-7)
        rms = new_rms
        if converged:
            return T, rms, frac, it, True
    return T, rms, frac, iters, False


def align(
    tree: SampleTree,
    points: np.ndarray,
    *,
    max_points: int = 20_000,
    max_correspondence_mm: float = 10.0,
    max_iterations: int = 50,
) -> Registration:
    """Fit rig points to the CAD: PCA in the conveyor plane, four in-plane flips, then ICP.

    Parameters
    ----------
    tree : SampleTree
    points : (N, 3) float64, rig frame, mm

    Returns
    -------
    Registration
        ``transform`` is T_cad_rig.

    Raises
    ------
    InvalidInput, InsufficientOverlap
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInput(f"points must be (N, 3), got {pts.shape}")
    if len(pts) < 100:
        raise InsufficientOverlap(f"only {len(pts)} points to fit (need 100)")
    coarse = _stride_subsample(pts, 2000)
    c_data = coarse.mean(axis=0)
    c_cad = tree.points.mean(axis=0)

    def principal_angle(xy: np.ndarray) -> float:
        cov = np.cov((xy - xy.mean(axis=0)).T)
        w, v = np.linalg.eigh(cov)
        a = v[:, np.argmax(w)]
        return float(np.arctan2(a[1], a[0]))

    yaw = principal_angle(tree.points[:, :2]) - principal_angle(coarse[:, :2])
    best: tuple[float, np.ndarray] | None = None
    # The principal axis fixes the yaw up to a half turn; mirror images are not
    # rigid, so the candidates are yaw and yaw + pi.
    for flip in (0.0, np.pi):
        R = _rot_z(yaw + flip)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = c_cad - R @ c_data
        # The coarse fit only has to pick the half turn and land in the basin.
        T, rms, frac, _, _ = _icp(tree, coarse, T, 15, 4 * max_correspondence_mm, tol_mm=1e-3)
        score = rms / max(frac, 1e-3)
        if best is None or score < best[0]:
            best = (score, T)
    assert best is not None
    fine = _stride_subsample(pts, max_points)
    T, rms, frac, iters, conv = _icp(tree, fine, best[1], max_iterations, max_correspondence_mm)
    return Registration(T, rms, frac, iters, conv, "converged" if conv else "max_iterations")


@dataclass(frozen=True)
class PointDeviation:
    name: str
    deviation_mm: float | None
    support: int
    verdict: str


@dataclass(frozen=True, eq=False)
class Deviations:
    """distances (N,) signed mm, comparison (per point), verdict."""

    distances: np.ndarray
    comparison: list[PointDeviation]
    verdict: str


def deviations(
    tree: SampleTree, points_cad: np.ndarray, comparison_points: list[Any]
) -> Deviations:
    """Signed point-to-plane distances and the deviation at each comparison point.

    ``comparison_points`` have ``name``, ``position_mm``, ``normal``,
    ``lower_mm``, ``upper_mm``, ``radius_mm`` and ``min_support``. The
    deviation at a point is the median of the pooled points' offsets along
    the CAD normal (robust to a few stray points).
    """
    pts = np.asarray(points_cad, dtype=np.float64)
    _, idx = tree.kdtree.query(pts) if len(pts) else (None, np.zeros(0, np.int64))
    dist = (
        np.einsum("ij,ij->i", pts - tree.points[idx], tree.normals[idx])
        if len(pts)
        else np.zeros(0)
    )
    cloud_tree = cKDTree(pts) if len(pts) else None
    out = []
    for cp in comparison_points:
        pos = np.asarray(cp.position_mm, dtype=np.float64)
        nrm = np.asarray(cp.normal, dtype=np.float64)
        near: np.ndarray = (
            np.asarray(cloud_tree.query_ball_point(pos, cp.radius_mm), np.int64)
            if cloud_tree is not None
            else np.zeros(0, np.int64)
        )
        support = len(near)
        if support < cp.min_support:
            out.append(PointDeviation(cp.name, None, support, "not_measurable"))
            continue
        dev = float(np.median((pts[np.sort(near)] - pos) @ nrm))
        ok = cp.lower_mm <= dev <= cp.upper_mm
        out.append(PointDeviation(cp.name, dev, support, "pass" if ok else "fail"))
    verdicts = {d.verdict for d in out}
    verdict = (
        "fail"
        if "fail" in verdicts
        else "not_measurable"
        if "not_measurable" in verdicts
        else "pass"
    )
    return Deviations(dist, out, verdict)

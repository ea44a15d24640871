"""The search for the pose of a part lying anywhere: hypotheses, refinement, finalists, fine fit.

:func:`align` runs the stages described in :mod:`inspection.alignment` and
returns an :class:`Alignment`.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..arrays import Points, Scalars, Transform
from ..errors import InsufficientOverlap, InvalidInput
from ..protocols import Triangles
from ..registration import (
    CadFaces,
    ClosestPointQuery,
    RegisterParams,
    Registration,
    register,
    validate_points,
)
from ..transforms import apply
from .model import AlignmentModel, alignment_model, as_triangles, footprint

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Candidate:
    """A refined pose hypothesis and its score (lower is better).

    Attributes
    ----------
    transform : (4, 4) float64
        ``T_cad_data`` after coarse refinement.
    score : float
        Mean truncated squared residual of the cloud's subsample, mm^2
        (the same truncation for every candidate).
    pose_index : int
        Index into ``AlignmentModel.poses``.
    angle_deg : float
        The starting rotation about the vertical.
    refined : bool
        A finalist: refined on the CAD tree and scored against the other
        finalists (scores of finalists and of the rest are not comparable).
    """

    transform: Transform
    score: float
    pose_index: int
    angle_deg: float
    refined: bool = False


@dataclass(frozen=True, eq=False)
class Alignment(Registration):
    """A :class:`Registration` found from an unknown starting pose.

    Attributes
    ----------
    ambiguous : bool
        Another pose, distinct from the chosen one, fits (almost) as well:
        the part looks symmetric to the sensor and the pose is not unique.
    candidates : tuple of Candidate
        The finalists (``refined``), best first, the first being the one
        refined into ``transform``; then the other distinct hypotheses with
        their coarse scores.
    """

    ambiguous: bool = False
    candidates: tuple[Candidate, ...] = ()


def _mid_extent(x: np.ndarray) -> np.ndarray:
    """Middle of the 1st-99th percentile range of ``x`` along its first axis."""
    lo, hi = np.percentile(x, [1.0, 99.0], axis=0)
    return 0.5 * (lo + hi)


def _rot_z(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose_distance(A: Transform, B: Transform, pts: Points) -> float:
    """RMS distance, mm, between the images of ``pts`` under two transforms."""
    a = apply(A, pts)
    b = apply(B, pts)
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def align(
    tree: ClosestPointQuery,
    points: Points,
    params: RegisterParams | None = None,
    *,
    model: AlignmentModel | None = None,
    cad: Triangles | None = None,
    weights: Scalars | None = None,
    faces: CadFaces | None = None,
    n_angles: int = 36,
    n_refine: int = 4,
    sample_points: int = 4000,
    refine_points: int = 500,
    score_points: int = 300,
    footprint_ratio: float = 0.7,
    clear_ratio: float = 2.0,
    ambiguity_ratio: float = 1.25,
    finalist_ratio: float = 2.0,
    n_finalists: int = 3,
    **register_keywords: Any,
) -> Alignment:
    """Find ``T_cad_data`` for a part lying anywhere, then refine it.

    Parameters
    ----------
    tree : ClosestPointQuery
        The CAD tree (``GridTree``); used for the final fine registration and,
        when neither ``model`` nor ``cad`` is given, as the source of geometry.
    points : (N, 3) float64, mm, data frame with z up (the rig frame)
        The measured cloud: the side of the part that faces the sensor.
    params : RegisterParams, optional
        The final fit's parameters; their ``seed`` and ``view_direction``
        drive the search too (with a view direction, every refinement counts
        a point whose closest face is turned away from the sensor as an
        outlier, so that a thin part modelled as a solid is not fitted half
        onto its underside). Default ``RegisterParams(escape_deg=None)``: the
        search covers the turn, so the final fit runs without its escape scan.
    model : AlignmentModel, optional
        From :func:`alignment_model`; build it once per part type and reuse
        it. Built from ``cad`` or ``tree`` when omitted.
    cad : CadModel, optional
        The geometry to build ``model`` from (any :class:`~inspection.protocols.Triangles`).
    weights : (N,) float64, optional
        Per-point input weights for the final registration.
    faces : CadFaces, optional
        The CAD's faces for the fits on ``tree`` (see :func:`register`);
        built from ``tree`` once when omitted.
    n_angles : int
        Rotations about the vertical tried per resting pose whose footprint
        (or the cloud's) has no clear major axis.
    n_refine : int
        Distinct hypotheses refined on the subsample.
    sample_points : int
        Size of the cloud's subsample used to score hypotheses.
    refine_points : int
        Size of the (smaller) subsample used to refine them.
    score_points : int
        Points of each resting pose's template placed per hypothesis to
        score it (a prefix of the template).
    footprint_ratio : float
        A footprint (x, y of the template or of the cloud) whose minor over
        major principal variance is at most this has a clear major axis;
        when both have one, a resting pose is tried at the two rotations
        that lay the axes on each other instead of ``n_angles``.
    clear_ratio : float
        Once two distinct hypotheses are refined, hypotheses whose score is
        more than this factor above the best one's are not refined.
    ambiguity_ratio : float
        A distinct finalist whose score is within this factor of the best
        makes the result ambiguous.
    finalist_ratio, n_finalists : float, int
        Up to ``n_finalists`` candidates scoring within ``finalist_ratio`` of
        the best after coarse refinement are refined again on the CAD tree
        and compared.
    **register_keywords
        Fields of :class:`RegisterParams` replacing those of ``params``
        (``align(tree, points, view_direction=(0.0, 0.0, 1.0))``).

    Returns
    -------
    Alignment

    Raises
    ------
    InvalidInput
        Bad points or parameters.
    InsufficientOverlap
        No hypothesis brings enough points near the CAD.
    """
    P = validate_points(points, min_points=30)
    p = params if params is not None else RegisterParams(escape_deg=None)
    if register_keywords:
        p = dataclasses.replace(p, **register_keywords)
    seed, view = p.seed, p.view_direction
    if faces is None and isinstance(tree, Triangles):
        faces = CadFaces.of(tree)
    if n_angles < 1 or n_refine < 1 or min(sample_points, refine_points, score_points) < 30:
        raise InvalidInput(
            "n_angles and n_refine must be >= 1, sample_points, refine_points and "
            "score_points >= 30"
        )
    if not np.isfinite(ambiguity_ratio) or ambiguity_ratio < 1.0:
        raise InvalidInput(f"ambiguity_ratio must be >= 1, got {ambiguity_ratio!r}")
    if not 0.0 <= footprint_ratio <= 1.0:
        raise InvalidInput(f"footprint_ratio must be in [0, 1], got {footprint_ratio!r}")
    if not np.isfinite(clear_ratio) or clear_ratio < 1.0:
        raise InvalidInput(f"clear_ratio must be >= 1, got {clear_ratio!r}")
    if model is None:
        model = alignment_model(as_triangles(cad if cad is not None else tree), seed=seed)
    rng = np.random.default_rng(seed)
    # Random order: every prefix of the subsample is a random sample too.
    sub = P[rng.choice(len(P), size=min(sample_points, len(P)), replace=False)]
    c_data = sub.mean(axis=0)
    data_tree = cKDTree(sub)
    # Hypothesis scores saturate at a few per cent of the part size, so that a
    # hypothesis is judged by how much of its template lands on the cloud.
    trunc = 0.03 * model.size_mm
    scan = np.arange(n_angles) * (2.0 * np.pi / n_angles)
    axis_data, elongation_data = footprint(sub[:, :2])
    # The cloud's principal directions in the plane (rows): a hypothesis puts
    # the middle of the template's extent along them on the middle of the
    # cloud's. The centroids would not do: the cloud's point density is
    # uneven (overlapping views), and a shift along a part's long axis is
    # the one the refinements correct most slowly.
    ca, sa = np.cos(axis_data), np.sin(axis_data)
    frame = np.array([[ca, sa], [-sa, ca]])
    mid_data = _mid_extent(sub[:, :2] @ frame.T)
    back = sub[:score_points]

    hyps: list[tuple[bool, float, int, float, np.ndarray]] = []
    # Poses whose hypotheses come from the footprints' axes: near enough to
    # be refined on the CAD tree directly (exact, and cheap near the surface).
    by_axes: set[int] = set()
    for k, pose in enumerate(model.poses):
        if max(pose.elongation, elongation_data) <= footprint_ratio:
            # Both footprints have a clear major axis: the rotation about the
            # vertical lays the template's axis on the cloud's, pointing one
            # way or the other (two hypotheses instead of a scan).
            a0 = (axis_data - pose.axis_rad) % (2.0 * np.pi)
            angles = np.array([a0, (a0 + np.pi) % (2.0 * np.pi)])
            by_axes.add(k)
        else:
            angles = scan
        c, s_ = np.cos(angles)[:, None], np.sin(angles)[:, None]
        # Per angle, the template turned about z (n, M) and the translation
        # t (n, 3) that maps it onto the cloud: x_data = Rz(theta) x_rest + t.
        full = pose.template
        rx = c * full[:, 0] - s_ * full[:, 1]
        ry = s_ * full[:, 0] + c * full[:, 1]
        mid_u = _mid_extent((rx * frame[0, 0] + ry * frame[0, 1]).T)
        mid_v = _mid_extent((rx * frame[1, 0] + ry * frame[1, 1]).T)
        shift = (mid_data[None, :] - np.stack([mid_u, mid_v], axis=1)) @ frame
        t = np.empty((len(angles), 3))
        t[:, :2] = shift
        t[:, 2] = c_data[2] - pose.centroid[2]
        # The template's points are independent samples: a prefix scores as
        # well as the whole, for less. Every angle in one query: (n, M, 3).
        tpl = full[:score_points]
        y = np.empty((len(angles), len(tpl), 3))
        y[:, :, 0] = c * tpl[:, 0] - s_ * tpl[:, 1] + t[:, :1]
        y[:, :, 1] = s_ * tpl[:, 0] + c * tpl[:, 1] + t[:, 1:2]
        y[:, :, 2] = tpl[:, 2] + t[:, 2:]
        d, _ = data_tree.query(y.reshape(-1, 3), distance_upper_bound=trunc)
        scores = np.mean(np.minimum(d, trunc).reshape(len(angles), -1) ** 2, axis=1)
        # And the other way round: the cloud turned into the resting frame,
        # against the whole template, so that a pose whose visible side covers
        # only part of the cloud (a panel on its edge) does not score well.
        bx = back[:, 0] - t[:, :1]
        by = back[:, 1] - t[:, 1:2]
        yb = np.empty((len(angles), len(back), 3))
        yb[:, :, 0] = c * bx + s_ * by
        yb[:, :, 1] = -s_ * bx + c * by
        yb[:, :, 2] = back[:, 2] - t[:, 2:]
        d, _ = cKDTree(full).query(yb.reshape(-1, 3), distance_upper_bound=trunc)
        scores += np.mean(np.minimum(d, trunc).reshape(len(angles), -1) ** 2, axis=1)
        # Hypotheses at neighbouring angles of a scan refine into the same
        # pose: the local minima of the score over the angle come first, so
        # that the refinement budget goes to distinct poses.
        if angles is scan:
            local_min = (scores <= np.roll(scores, 1)) & (scores <= np.roll(scores, -1))
        else:
            local_min = np.ones(len(angles), dtype=bool)
        for a in range(len(angles)):
            # T_data_cad = [Rz(theta) | t] T_rest_cad.
            T_dc = np.eye(4)
            T_dc[:3, :3] = _rot_z(angles[a])
            T_dc[:3, 3] = t[a]
            T_dc = T_dc @ pose.transform
            hyps.append(
                (
                    not local_min[a],
                    float(scores[a]),
                    k,
                    float(np.degrees(angles[a])),
                    np.linalg.inv(T_dc),
                )
            )
    hyps.sort(key=lambda h: (h[0], h[1], h[2], h[3]))
    best_hyp = hyps[0][1]
    log.debug("hypotheses: %s", [(h[2], round(h[3]), round(h[1], 2)) for h in hyps[:8]])

    # Coarse refinement of the best hypotheses (on the tree or the sampled surface).
    refined: list[Candidate] = []
    residuals: list[np.ndarray] = []
    tried = 0
    for _, score, k, ang, T in hyps:
        if tried >= 3 * n_refine or len(refined) >= n_refine:
            break
        if len(refined) >= 2 and score > clear_ratio * max(best_hyp, 1e-12 * trunc * trunc):
            # The rest place clearly less of their template on the cloud than
            # the best: two refined rivals are enough to judge ambiguity.
            break
        tried += 1
        # The search over the turn is this function's: its refinements run
        # without register's own scan of an unconstrained rotation.
        try:
            reg = register(
                tree if k in by_axes else model.surface,
                sub[:refine_points],
                init=T,
                loss="tukey",
                max_iterations=25,
                initial_subset=min(128, refine_points),
                max_subset=None,
                max_distance_mm=max(model.size_mm, 1.0),
                min_scale_mm=0.05,
                tolerance_rad=2e-4,
                tolerance_mm=2e-2,
                subset_tolerance_factor=10.0,
                seed=seed,
                view_direction=view,
                escape_deg=None,
                faces=faces if k in by_axes else None,
            )
        except InsufficientOverlap:
            continue
        Tr = reg.transform
        if any(
            _pose_distance(Tr, c.transform, sub[:refine_points]) < 0.02 * model.size_mm
            for c in refined
        ):
            continue
        refined.append(Candidate(Tr, 0.0, k, ang))
        residuals.append(reg.residuals)
        log.debug(
            "hypothesis pose %d at %.0f deg: score %.3g -> rms %.3f", k, ang, score, reg.rms_mm
        )
    if not refined:
        raise InsufficientOverlap("no pose hypothesis brings the cloud near the CAD")

    scored = _score(refined, residuals, refined=False)

    # Finalists: the candidates that come close to the best are refined again
    # on the CAD tree (exact distances) and re-scored, so that a hypothesis
    # the coarse stage left a few degrees off is not mistaken for a rival.
    finalists: list[Candidate] = []
    final_res: list[np.ndarray] = []
    for cand in scored:
        if len(finalists) >= n_finalists or cand.score > finalist_ratio * scored[0].score:
            break
        try:
            reg = register(
                tree,
                sub[:refine_points],
                init=cand.transform,
                loss="tukey",
                max_iterations=40,
                initial_subset=refine_points,
                max_subset=None,
                max_distance_mm=max(model.size_mm, 1.0),
                seed=seed,
                view_direction=view,
                escape_deg=None,
                faces=faces,
            )
        except InsufficientOverlap:
            continue
        if any(
            _pose_distance(reg.transform, f.transform, sub[:refine_points]) < 0.02 * model.size_mm
            for f in finalists
        ):
            continue
        finalists.append(Candidate(reg.transform, 0.0, cand.pose_index, cand.angle_deg))
        final_res.append(reg.residuals)
    if finalists:
        ranked = _score(finalists, final_res, refined=True)
    else:
        ranked = scored[:1]
    best = ranked[0]
    ambiguous = len(ranked) > 1 and ranked[1].score <= ambiguity_ratio * best.score
    fine = register(tree, P, p, init=best.transform, weights=weights, faces=faces)
    log.debug(
        "align: %d candidates, %d finalists, best %.4g, runner-up %s, ambiguous %s",
        len(scored),
        len(ranked),
        best.score,
        f"{ranked[1].score:.4g}" if len(ranked) > 1 else "none",
        ambiguous,
    )
    finals = {(f.pose_index, f.angle_deg) for f in ranked}
    scored = ranked + [c for c in scored if (c.pose_index, c.angle_deg) not in finals]
    fields = {f.name: getattr(fine, f.name) for f in dataclasses.fields(Registration)}
    return Alignment(**fields, ambiguous=bool(ambiguous), candidates=tuple(scored))


def _score(
    cands: list[Candidate], residuals: list[np.ndarray], *, refined: bool
) -> list[Candidate]:
    """Re-score candidates with one truncation (3 robust scales of the best fit), best first."""
    sig = min(1.4826 * float(np.median(np.abs(r))) for r in residuals)
    tau = 3.0 * max(sig, 0.01)
    out = [
        Candidate(
            c.transform,
            float(np.mean(np.minimum(r * r, tau * tau))),
            c.pose_index,
            c.angle_deg,
            refined,
        )
        for c, r in zip(cands, residuals, strict=True)
    ]
    return sorted(out, key=lambda c: (c.score, c.pose_index, c.angle_deg))

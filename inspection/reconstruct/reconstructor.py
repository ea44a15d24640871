"""The reconstructor of one rig: its passes over a frame set, from frames to a cloud.

A :class:`Reconstructor` holds what depends on the rig alone (the rectified
pairs, the volume searched, the belt's disparities, and the thread pool the
pairs are matched on), built once per rig by :meth:`Reconstructor.build`.
Each pass matches every pair of the rig on a thread of its own, then fuses
the pairs' points into one :class:`~.result.Cloud`:

1. **first pass** (:meth:`Reconstructor.match`, or a call): per stereo pair,
   the coarse matching and the square windows (:mod:`.matching`), then the
   warped windows and the triangulation (:mod:`.warping`); with a
   :class:`~.guided.Guide`, the windows follow it and the ring pairs join in
   (:mod:`.guided`). A *sparse* first pass (``match(frames, sparse=True)``)
   only places the guide: the warped passes refit, and the cloud holds, the
   windows of every ``sparse_rows``-th row (the guided pass starts from every
   square window, not from the warped ones); :meth:`Reconstructor.sparse_cloud`
   matches those rows only, square windows included, for a cloud that only
   places the part;
2. **guided pass** (:meth:`Reconstructor.guided`): from the first pass's
   :class:`Matching`, the warped windows again, following a guide at the pose
   fitted to the first cloud, and the ring pairs matched from the guide;
3. **the bends again** (:meth:`Reconstructor.rematch_bends`): from the guided
   pass's :class:`Matching`, the windows on bends and at the outline, with a
   guide at the pose fitted to the guided cloud.

Every pass ends in the fusion (:mod:`.fusion`). What a pass found is handed
to the caller as a :class:`Matching`, a value the caller passes to the next
pass; passes never change it, and a cloud never carries it.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import InspectionError, InvalidInput
from ..rig import VOLUME_MM, Rig
from .fusion import fuse
from .guided import Guide, Prior, finish_guided, rematch_pair, ring_pair
from .matching import PairResult, PairState, match_pair, skipped
from .pairs import RectifiedPair, belt_disparity, rectified_pair
from .params import SATURATION_DN, ReconstructParams
from .result import (
    FLAG_EMPTY,
    FLAG_LOW_TEXTURE,
    FLAG_PAIR_SKIPPED,
    FLAG_SATURATED,
    FLAG_TOO_DARK,
    Cloud,
    ReconstructionReport,
)
from .warping import finish_pair

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Reconstructor:
    """The per-rig state of :func:`reconstruct`: rectification maps of every stereo pair.

    Build once per rig with :meth:`build` and pass it to every call. It owns
    the thread pool its pairs are matched on (``params.threads > 1``): the
    pool's idle threads end when the reconstructor is closed
    (:meth:`close`, or a ``with`` block) or garbage-collected. A pool's
    threads do not survive a fork, so a reconstructor built before a fork
    refuses to run in the child: build one there.

    Attributes
    ----------
    rig : Rig
    params : ReconstructParams
    pairs : tuple of RectifiedPair
    volume_lo, volume_hi : (3,) float64, mm
        The box searched without a prior (rig frame).
    foreground_disparity : tuple of (H, W) float32
        Per pair, the coarse disparity above which a pixel is part, not belt.
    guide_pairs : tuple of RectifiedPair
        Pairs matched only with a guide (``guided_ring_pairs``); their points
        follow those of ``pairs`` in :attr:`Cloud.pair`.
    executor : ThreadPoolExecutor or None
        The pool the pairs are matched and fused on (None: ``threads == 1``).
    pid : int
        The process the pool was made in.
    """

    rig: Rig
    params: ReconstructParams
    pairs: tuple[RectifiedPair, ...]
    volume_lo: npt.NDArray[np.float64]
    volume_hi: npt.NDArray[np.float64]
    foreground_disparity: tuple[npt.NDArray[np.float32], ...]
    guide_pairs: tuple[RectifiedPair, ...] = ()
    executor: ThreadPoolExecutor | None = field(default=None, repr=False)
    pid: int = field(default_factory=os.getpid, repr=False)

    @classmethod
    def build(cls, rig: Rig, params: ReconstructParams | None = None) -> Reconstructor:
        """Precompute the rectification of each of ``rig.stereo_pairs``, and make the pool
        that matches them (``params.threads`` threads, started when first used)."""
        if not isinstance(rig, Rig):
            raise InvalidInput(f"rig must be a Rig, got {type(rig).__name__}")
        params = params or ReconstructParams()
        if not isinstance(params, ReconstructParams):
            raise InvalidInput("params must be a ReconstructParams")
        m = params.volume_margin_mm
        lo = np.array([-VOLUME_MM[0] / 2 - m, -VOLUME_MM[1] / 2 - m, 0.0])
        hi = np.array([VOLUME_MM[0] / 2 + m, VOLUME_MM[1] / 2 + m, params.z_max_mm])
        wanted = rig.stereo_pairs + (rig.ring_pairs if params.ring_pairs else ())
        pairs = [rectified_pair(rig, a, b, lo, hi) for a, b in wanted]
        guided_only = params.guided_ring_pairs and not params.ring_pairs
        guide_pairs = tuple(
            rectified_pair(rig, a, b, lo, hi) for a, b in rig.ring_pairs if guided_only
        )
        # The belt at z = 0 seen through a rectified pixel has the disparity of
        # that depth; a part pixel is one whose coarse disparity is above that of
        # the plane z = z_min (less the coarse matching's own uncertainty, ~1 mm).
        z_fg = max(params.z_min_mm - 1.5, 0.0)
        fg = tuple(belt_disparity(pair, z_fg) for pair in pairs)
        log.debug(
            "reconstructor built for rig %s: %s",
            rig.id,
            [(p.name, p.size, round(p.baseline_mm, 1)) for p in pairs],
        )
        # The pairs are independent and their heavy steps (OpenCV, the numba
        # kernels) release the GIL: one thread per pair, each kernel on one thread,
        # uses the cores without nesting numba's parallel layer.
        pool = (
            ThreadPoolExecutor(params.threads, "reconstruct-pair") if params.threads > 1 else None
        )
        return cls(rig, params, tuple(pairs), lo, hi, fg, guide_pairs, pool)

    def close(self) -> None:
        """End the pool's threads (waiting for running passes); the reconstructor
        cannot run with more than one thread afterwards."""
        if self.executor is not None:
            self.executor.shutdown(wait=True)

    def __enter__(self) -> Reconstructor:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __call__(
        self,
        frames: Sequence[npt.NDArray[np.uint8]],
        *,
        prior: Prior | None = None,
        guide: Guide | None = None,
    ) -> Cloud:
        """Reconstruct one frame set; see :func:`reconstruct`. To match the same frames
        again later (:meth:`guided`), use :meth:`match` instead."""
        self._check_guide(guide)
        cloud, _ = self._first_pass(frames, prior, guide, keep_frames=False)
        return cloud

    def match(
        self,
        frames: Sequence[npt.NDArray[np.uint8]],
        *,
        prior: Prior | None = None,
        guide: Guide | None = None,
        sparse: bool = False,
    ) -> tuple[Cloud, Matching]:
        """Reconstruct one frame set, and hand out what its matching found.

        The cloud is the one a call gives, to the bit. The :class:`Matching`
        is where :meth:`guided` starts matching the same frames again (with a
        ``guide``, also :meth:`rematch_bends`); it keeps a copy of the
        frames when the reconstructor has :attr:`guide_pairs`.

        With ``sparse`` (no ``guide``), the cloud is one to place a guide
        with: the warped passes refit, and the cloud holds, the windows of
        every ``params.sparse_rows``-th rectified row only, each checked
        against every window's disparity map. The :class:`Matching` is the
        same as without it (every square window), so :meth:`guided` gives
        the same cloud from either.

        Raises
        ------
        InvalidInput
            ``sparse`` with a ``guide``.
        """
        self._check_guide(guide)
        if sparse and guide is not None:
            raise InvalidInput("sparse=True places a guide: it is for the unguided first pass")
        return self._first_pass(frames, prior, guide, keep_frames=True, sparse=sparse)

    def sparse_cloud(
        self, frames: Sequence[npt.NDArray[np.uint8]], *, prior: Prior | None = None
    ) -> Cloud:
        """A cloud to place the part with, and nothing more: every stage, the square
        windows included, on every ``params.sparse_rows``-th rectified row only.

        The rows between are neither refined nor triangulated; the warped
        windows follow, and the other pair's check reads, the field of the
        sparse rows filled across them. The windows are warped as
        ``params.sparse_cloud_warp_slope`` and ``sparse_cloud_warp_passes``
        say, not as the first pass's. Nothing is kept for a :meth:`guided`
        pass: ``match(frames, sparse=True)`` gives a cloud of the same rows
        and what the guided pass starts from, at the cost of every square
        window.
        """
        cloud, _ = self._first_pass(frames, prior, None, keep_frames=False, rows_only=True)
        return cloud

    def guided(self, matching: Matching, guide: Guide) -> tuple[Cloud, Matching]:
        """Match the frames of ``matching`` again, with the windows following ``guide``.

        Starts from the coarse and square-window matching of the first pass
        (``matching``, from :meth:`match` of this reconstructor): only the
        warped passes, the triangulation and the fusion run again, and the
        ring pairs (:attr:`guide_pairs`) are matched from the guide. The
        cloud is the one ``self(frames, guide=guide)`` gives, to the bit; the
        :class:`Matching` is where :meth:`rematch_bends` starts.

        Raises
        ------
        InvalidInput
            ``matching`` is not a :class:`Matching` of this reconstructor, or
            ``guide`` is not a :class:`Guide`.
        """
        if guide is None:
            raise InvalidInput("guided() needs a Guide")
        self._check_guide(guide)
        self._check_matching(matching, "guided")
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        n = len(self.pairs)
        lo, hi = self.volume_lo, self.volume_hi

        def one_pair(k: int) -> PairResult:
            if k >= n:
                pair = self.guide_pairs[k - n]
                if not (matching.usable[pair.left] and matching.usable[pair.right]):
                    return skipped(self.rig, pair, matching.usable)
                return ring_pair(pair, matching.frames, guide, lo, hi, self.params, timings, k)
            res = matching.results[k]
            if res.state is None:  # skipped, or nothing of the part seen
                return res
            return finish_guided(self.pairs[k], res.state, self.params, timings, k, guide)

        results = self._per_pair(one_pair, n + len(self.guide_pairs))
        return self._assemble(replace(matching, results=tuple(results)), timings, t0)

    def rematch_bends(self, matching: Matching, guide: Guide) -> tuple[Cloud, Matching]:
        """Match the windows on bends of a guided pass again, with ``guide`` at a better pose.

        A guided window takes its shape from the guide. Where the guide is
        placed a little off, a bend's shape lands beside the real one and
        the window's fit is pulled towards the guide (see "Matching the
        bends again" in :mod:`.guided`). After the guided cloud has been
        fitted, this matches again only the windows that span a bend or
        reach the outline of the new guide, starting from the guided fit;
        every other window keeps its match. Triangulation and fusion run
        again.

        ``matching`` is what :meth:`guided` (or this method, or :meth:`match`
        with a guide) returned.

        Raises
        ------
        InvalidInput
            ``matching`` is not a guided :class:`Matching` of this
            reconstructor, or ``guide`` is not a :class:`Guide`.
        """
        if guide is None:
            raise InvalidInput("rematch_bends() needs a Guide")
        self._check_guide(guide)
        self._check_matching(matching, "rematch_bends")
        if not any(r.guided is not None for r in matching.results):
            raise InvalidInput("the matching holds no guided pass: pass what guided() returned")
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        pairs = self.pairs + self.guide_pairs

        def one_pair(k: int) -> PairResult:
            res = matching.results[k]
            if res.state is None or res.guided is None:
                return res
            return rematch_pair(pairs[k], res.state, res.guided, self.params, timings, k, guide)

        results = self._per_pair(one_pair, len(matching.results))
        return self._assemble(replace(matching, results=tuple(results)), timings, t0)

    # -- the steps ------------------------------------------------------------

    def _first_pass(
        self,
        frames: Any,
        prior: Prior | None,
        guide: Guide | None,
        keep_frames: bool,
        sparse: bool = False,
        rows_only: bool = False,
    ) -> tuple[Cloud, Matching]:
        p = self.params
        # The pairs' own stages see the sparse rows as the rows refined, and the sparse
        # cloud's own warping.
        per_pair = (
            replace(
                p,
                row_stride=max(p.row_stride, p.sparse_rows),
                warp_slope=p.sparse_cloud_warp_slope,
                warp_passes=p.sparse_cloud_warp_passes,
            )
            if rows_only
            else p
        )
        imgs = _check_frames(self.rig, frames)
        timings: dict[str, float] = {}
        t0 = time.perf_counter()

        frame_flags = []
        usable = []
        for img in imgs:
            f, ok = _frame_flags(img, p)
            frame_flags.append(tuple(sorted(f)))
            usable.append(ok)
        all_flags = set().union(*[set(f) for f in frame_flags])
        timings["check"] = (time.perf_counter() - t0) * 1e3

        z_hi = min(p.z_max_mm, prior.z_max_mm) if prior is not None else p.z_max_mm
        lo = self.volume_lo.copy()
        hi = self.volume_hi.copy()
        hi[2] = max(z_hi, p.z_min_mm + 1.0)

        n = len(self.pairs)

        def one_pair(k: int) -> PairResult:
            if k >= n:
                assert guide is not None  # such pairs are only asked for with a guide
                pair = self.guide_pairs[k - n]
                if not (usable[pair.left] and usable[pair.right]):
                    return skipped(self.rig, pair, usable)
                return ring_pair(pair, imgs, guide, self.volume_lo, self.volume_hi, p, timings, k)
            pair = self.pairs[k]
            t1 = time.perf_counter()
            if not (usable[pair.left] and usable[pair.right]):
                return skipped(self.rig, pair, usable)
            left, right = imgs[pair.left], imgs[pair.right]
            out = match_pair(
                pair, self.foreground_disparity[k], left, right, lo, hi, per_pair, timings, k
            )
            if isinstance(out, PairState):
                if guide is not None:
                    out = finish_guided(pair, out, p, timings, k, guide)
                else:
                    out = finish_pair(pair, out, per_pair, timings, k, sparse=sparse)
            timings[f"pair{pair.name}"] = (time.perf_counter() - t1) * 1e3
            return out

        results = self._per_pair(one_pair, n + (len(self.guide_pairs) if guide is not None else 0))
        if any(r.report.skipped for r in results):
            all_flags.add(FLAG_PAIR_SKIPPED)
        # The pairs matched only with a guide need the frames again.
        kept = tuple(img.copy() for img in imgs) if keep_frames and self.guide_pairs else ()
        matching = Matching(
            self, tuple(results), tuple(frame_flags), frozenset(all_flags), kept, tuple(usable)
        )
        return self._assemble(matching, timings, t0)

    def _per_pair(self, one_pair: Callable[[int], PairResult], n: int) -> list[PairResult]:
        """``one_pair(k)`` for the first ``n`` of ``pairs + guide_pairs``, on the pool."""
        pool = self._pool()
        if pool is not None and n > 1:
            return list(pool.map(one_pair, range(n)))
        return [one_pair(k) for k in range(n)]

    def _assemble(
        self, matching: Matching, timings: dict[str, float], t0: float
    ) -> tuple[Cloud, Matching]:
        """Fuse the pairs' points into the cloud."""
        t = time.perf_counter()
        pairs = self.pairs + self.guide_pairs
        points, weights, which, reports = fuse(pairs, matching.results, self.params, self._pool())
        timings["fuse"] = (time.perf_counter() - t) * 1e3
        timings["total"] = (time.perf_counter() - t0) * 1e3
        flags = set(matching.flags)
        if len(points) == 0:
            flags.add(FLAG_EMPTY)
        report = ReconstructionReport(
            tuple(sorted(flags)), matching.frame_flags, tuple(reports), len(points), timings
        )
        log.debug(
            "reconstructed %d points in %.0f ms, flags %s",
            len(points),
            timings["total"],
            report.flags,
        )
        return Cloud(points, weights, which, report, self.rig.id), matching

    def _pool(self) -> ThreadPoolExecutor | None:
        if self.executor is not None and os.getpid() != self.pid:
            raise InspectionError(
                "this Reconstructor was built in another process (its pool's threads do not "
                "survive a fork): build one in this process"
            )
        return self.executor

    def _check_guide(self, guide: Guide | None) -> None:
        if guide is not None and not isinstance(guide, Guide):
            raise InvalidInput(f"guide must be a Guide, got {type(guide).__name__}")
        if guide is not None and self.params.symmetric:
            raise InvalidInput("a guide warps the left view's windows: not with symmetric=True")

    def _check_matching(self, matching: Matching, method: str) -> None:
        if not isinstance(matching, Matching):
            raise InvalidInput(
                f"{method}() needs the Matching that match() returned, "
                f"got {type(matching).__name__}"
            )
        if matching.reconstructor is not self:
            raise InvalidInput(
                "the matching was made by another reconstructor: pass the Matching this "
                "reconstructor's match() returned"
            )


@dataclass(frozen=True, eq=False)
class Matching:
    """What one pass over a frame set found, pair by pair: where the next pass starts.

    Made by :meth:`Reconstructor.match` (the first pass), then by
    :meth:`Reconstructor.guided` and :meth:`Reconstructor.rematch_bends`,
    and taken by the latter two of the same reconstructor. No pass changes
    it: one matching can start several passes.

    Attributes
    ----------
    reconstructor : Reconstructor
        The one that made it, the only one that can take it.
    results : tuple of PairResult
        Per pair of ``reconstructor.pairs`` (then of its ``guide_pairs``
        once guided): the pair's points and maps, and where its next pass
        starts (its square windows and, guided, its guided fit; crops of the
        normalised images included).
    frame_flags : tuple of tuple of str
        Per camera, the flags of its frame.
    flags : frozenset of str
        The frame set's flags.
    frames : tuple of (H, W) uint8
        Copies of the frames, for the pairs matched only with a guide
        (empty when the reconstructor has none).
    usable : tuple of bool
        Per camera, whether its frame can be matched.
    """

    reconstructor: Reconstructor
    results: tuple[PairResult, ...]
    frame_flags: tuple[tuple[str, ...], ...]
    flags: frozenset[str]
    frames: tuple[npt.NDArray[np.uint8], ...] = ()
    usable: tuple[bool, ...] = ()


def reconstruct(
    rig: Rig,
    frames: Sequence[npt.NDArray[np.uint8]],
    *,
    prior: Prior | Any | None = None,
    params: ReconstructParams | None = None,
    reconstructor: Reconstructor | None = None,
    guide: Guide | None = None,
) -> Cloud:
    """Reconstruct a point cloud of the part from the four flash frames.

    Parameters
    ----------
    rig : Rig
        The calibrated rig that took the frames (:meth:`Rig.default` on the line).
    frames : sequence of four (H, W) uint8
        One grey image per camera, in the rig's camera order, each of its
        camera's size.
    prior : Prior or CadModel or trimesh.Trimesh, optional
        What is known of the part: a mesh is turned into a :class:`Prior` with
        :meth:`Prior.from_cad` (the band of heights it can occupy).
    params : ReconstructParams, optional
        Only used when ``reconstructor`` is not given.
    reconstructor : Reconstructor, optional
        Precomputed per-rig state (build it once per rig; built here otherwise).
    guide : Guide, optional
        The part's CAD at its fitted pose: the matching windows follow its
        shape (see :mod:`.guided`). Give it on a second pass over the same
        frames, after aligning the first cloud.

    Returns
    -------
    Cloud
        Points in the rig frame (mm) with weights and a report. Frames that
        cannot give points (all dark, all saturated, no texture, no part)
        give an empty cloud flagged ``"empty"`` with the reason in its flags.

    Raises
    ------
    InvalidInput
        Wrong number of frames, wrong size, dtype or dimensions, or a
        reconstructor built for another rig.
    """
    if not isinstance(rig, Rig):
        raise InvalidInput(f"rig must be a Rig, got {type(rig).__name__}")
    if reconstructor is None:
        with Reconstructor.build(rig, params) as own:
            return own(frames, prior=_prior(prior), guide=guide)
    if not isinstance(reconstructor, Reconstructor):
        raise InvalidInput("reconstructor must be a Reconstructor")
    if reconstructor.rig.id != rig.id:
        raise InvalidInput(f"reconstructor was built for rig {reconstructor.rig.id}, not {rig.id}")
    return reconstructor(frames, prior=_prior(prior), guide=guide)


def _prior(prior: Prior | Any | None) -> Prior | None:
    if prior is not None and not isinstance(prior, Prior):
        return Prior.from_cad(prior)
    return prior


def _check_frames(rig: Rig, frames: Any) -> list[npt.NDArray[np.uint8]]:
    if isinstance(frames, np.ndarray) and frames.ndim == 3:
        frames = list(frames)
    if not isinstance(frames, (list, tuple)):
        raise InvalidInput(
            f"frames must be a sequence of {len(rig.cameras)} images, got {type(frames).__name__}"
        )
    if len(frames) != len(rig.cameras):
        raise InvalidInput(f"need {len(rig.cameras)} frames (one per camera), got {len(frames)}")
    out = []
    for i, (img, cam) in enumerate(zip(frames, rig.cameras, strict=True)):
        if not isinstance(img, np.ndarray):
            raise InvalidInput(f"frame {i} must be a numpy array, got {type(img).__name__}")
        if img.dtype != np.uint8:
            raise InvalidInput(f"frame {i} must be uint8 (8-bit grey), got {img.dtype}")
        if img.ndim != 2:
            raise InvalidInput(f"frame {i} must be a 2-D grey image, got shape {img.shape}")
        if img.shape != cam.shape:
            raise InvalidInput(
                f"frame {i} has shape {img.shape}, camera {cam.name} takes {cam.shape} (H, W)"
            )
        out.append(np.ascontiguousarray(img))
    return out


def _frame_flags(img: npt.NDArray[np.uint8], p: ReconstructParams) -> tuple[set[str], bool]:
    """Flags of one frame, and whether it is usable at all."""
    flags: set[str] = set()
    usable = True
    small = img[::4, ::4]
    if np.percentile(small, 99) < p.dark_dn:
        flags.add(FLAG_TOO_DARK)
        usable = False
    sat = float(np.mean(small >= SATURATION_DN))
    if sat > p.saturated_fraction:
        flags.add(FLAG_SATURATED)
        usable = usable and sat <= min(1.0, 2 * p.saturated_fraction) and sat < 0.99
    if usable:
        # Texture: median absolute difference of horizontal neighbours among
        # unsaturated pixels (the speckle gives tens of DN).
        row = small.astype(np.int16)
        diff = np.abs(np.diff(row, axis=1))[(small[:, 1:] < SATURATION_DN)]
        if diff.size == 0 or float(np.median(diff)) < p.min_contrast_dn:
            flags.add(FLAG_LOW_TEXTURE)
            usable = False
    return flags, usable


__all__ = ["Matching", "Reconstructor", "reconstruct"]

"""Phase unwrapping against the CAD, and the regions it cannot unwrap.

The CAD at the part's pose predicts the phase difference ``4 pi z_cad / L``
(L the synthetic wavelength); the measured wrapped phase minus the
prediction, wrapped, is the deviation's phase ``r``. Wherever the part is
within a quarter of L of the CAD, ``|r| < pi`` and ``z = z_cad + r L / (4 pi)``
needs no unwrapping at all, across any step of the CAD. Where it is not,
``r`` wraps: a closed contour of 2 pi jumps encloses the region beyond the
limit. :func:`orders` finds such regions as the connected parts of the
field that only jumps separate from the main part, and gives each its
order (how many 2 pi it lies off); the shape there is not measured, the
region is reported.

The order is only carried along measurable pixels. A steep dent's flank
lowers the coherence of the averaged phase (its phase turns within the
average), and the contour of 2 pi jumps can lie inside that unmeasurable
ring: the dent's core is then cut off from the surface around it, and
nothing in the phase tells how many 2 pi lie between them. Such a region is
*unreached*: it lies on the same CAD surface as the main region (no CAD
edge separates them), so the CAD prior does not tell its order either, and
taking it as order 0 would read a deviation beyond the limit in a wrong
order.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


def wrap(phase: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Phase wrapped into (-pi, pi]."""
    return np.angle(np.exp(1j * phase))


@dataclass(frozen=True)
class Orders:
    """How many 2 pi each pixel's residual lies off its segment's main region.

    Attributes
    ----------
    order : (n, n) int64
        0 on each segment's main region; the region's order elsewhere; 0 where
        not valid.
    region : (n, n) int64
        Region label per pixel (-1 where not valid).
    known : (n, n) bool
        Valid pixels whose order is known (their region is large enough and
        reached from the main region of its group).
    unreached : (n, n) bool
        Valid pixels of regions large enough to be more than noise that no path
        of valid pixels joins to the main region of their group: of unknown order.
    """

    order: npt.NDArray[np.int64]
    region: npt.NDArray[np.int64]
    known: npt.NDArray[np.bool_]
    unreached: npt.NDArray[np.bool_]


def orders(
    residual: npt.NDArray[np.float64],
    valid: npt.NDArray[np.bool_],
    *,
    min_region_px: int,
    groups: npt.NDArray[np.int64] | None = None,
) -> Orders:
    """Split the valid pixels into regions separated by 2 pi jumps of ``residual``.

    A *region* is connected through valid neighbours whose residuals differ by
    less than pi. A *group* is what the CAD prior holds at order 0 as a whole:
    ``groups`` labels each pixel (one label per piece of CAD surface that no CAD
    edge cuts; -1 off them); without it, each set of valid pixels connected
    through valid neighbours is a group of its own. The largest region of a group
    has order 0; crossing a jump from ``a`` to ``b`` changes the order by
    ``-round((r_b - r_a) / 2 pi)``. Regions smaller than ``min_region_px``
    (speckle noise) are left unknown; larger ones that no path of valid pixels
    joins to their group's main region are left unknown and marked unreached.

    Parameters
    ----------
    residual : (n, m) float64, rad, wrapped
    valid : (n, m) bool
    min_region_px : int
    groups : (n, m) int64, optional
        Every valid pixel must have a label >= 0.
    """
    n, m = residual.shape
    idx = np.arange(n * m).reshape(n, m)
    pairs = []
    for a, b in (
        (idx[:, :-1], idx[:, 1:]),
        (idx[:-1, :], idx[1:, :]),
    ):
        a = a.ravel()
        b = b.ravel()
        both = valid.ravel()[a] & valid.ravel()[b]
        pairs.append((a[both], b[both]))
    ea = np.concatenate([p[0] for p in pairs])
    eb = np.concatenate([p[1] for p in pairs])
    r = residual.ravel()
    step = r[eb] - r[ea]
    jump = np.abs(step) > np.pi

    def components(sel: npt.NDArray[np.bool_]) -> npt.NDArray[np.int64]:
        g = coo_matrix((np.ones(int(sel.sum())), (ea[sel], eb[sel])), shape=(n * m, n * m))
        return connected_components(g, directed=False)[1].astype(np.int64)

    region = components(~jump)
    v = valid.ravel()
    if groups is None:
        group = components(np.ones_like(jump))
    else:
        group = np.asarray(groups, dtype=np.int64).ravel()
    sizes = np.bincount(region[v], minlength=n * m)

    # Order changes between regions across the jumps: the most common one per pair.
    ja, jb = region[ea[jump]], region[eb[jump]]
    delta = -np.rint(step[jump] / (2.0 * np.pi)).astype(np.int64)
    links: dict[int, list[tuple[int, int]]] = {}
    if len(ja):
        keys = np.stack([ja, jb, delta], axis=1)
        uniq, counts = np.unique(keys, axis=0, return_counts=True)
        best: dict[tuple[int, int], tuple[int, int]] = {}
        for (p, q, d), c in zip(uniq.tolist(), counts.tolist(), strict=True):
            if p == q:
                continue
            key = (p, q) if p < q else (q, p)
            dd = d if p < q else -d
            if key not in best or c > best[key][1]:
                best[key] = (dd, c)
        for (p, q), (d, _) in best.items():
            links.setdefault(p, []).append((q, d))
            links.setdefault(q, []).append((p, -d))

    order_of: dict[int, int] = {}
    for g in np.unique(group[v]):
        members = np.unique(region[v & (group == g)])
        main = int(members[np.argmax(sizes[members])])
        order_of[main] = 0
        queue = deque([main])
        while queue:
            p = queue.popleft()
            for q, d in links.get(p, []):
                if q not in order_of and sizes[q] >= min_region_px:
                    order_of[q] = order_of[p] + d
                    queue.append(q)
    lookup = np.full(n * m, np.iinfo(np.int64).min, dtype=np.int64)
    for k, o in order_of.items():
        lookup[k] = o
    per_pixel = lookup[region]
    large = sizes[region] >= min_region_px
    reached = per_pixel != np.iinfo(np.int64).min
    known = v & reached & large
    return Orders(
        order=np.where(known, per_pixel, 0).reshape(n, m),
        region=np.where(v, region, -1).reshape(n, m),
        known=known.reshape(n, m),
        unreached=(v & ~reached & large).reshape(n, m),
    )

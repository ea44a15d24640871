"""RPS (3-2-1) alignment: the pose that puts the measured datum features on their nominals.

A reference point system names datum features and the directions each one
fixes (a hole fixing x and y, a slot fixing y, three surface points fixing
z): six constraints in all for the classic 3-2-1 scheme. Every datum
direction ``d`` gives one residual ``d . (T m - p)`` between the measured
feature ``m`` (data frame) and its nominal ``p`` (CAD frame); the transform
minimises their weighted squares by Gauss-Newton on a twist about the
datums' centroid. With six independent constraints the solution is exact
(every residual zero); with more it is the weighted least-squares one, and
each datum's residual is reported.

A scheme that leaves a direction free (five constraints, or three surface
points in a line) is invalid input for :func:`rps_align`, and the error
names the free direction. :func:`rps_align` with ``hold=init`` instead
moves the given pose (a best fit) by the smallest twist that satisfies the
datums: the datums are held, the directions they leave free stay as the
best fit put them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..arrays import Transform
from ..errors import InvalidInput

__all__ = ["ALIGNMENTS", "Datum", "DatumResidual", "RpsAlignment", "RpsScheme", "rps_align"]

ALIGNMENTS = ("best_fit", "rps", "best_fit_rps")
"""A part's alignment: the best fit to the whole cloud; the RPS alone (the datums fix
every direction); the best fit with the datums held (they fix what they fix, the
best fit the rest)."""

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
_NAMES = (
    "rotation about x",
    "rotation about y",
    "rotation about z",
    "translation along x",
    "translation along y",
    "translation along z",
)
# A direction of the twist whose eigenvalue is below this fraction of the largest is free.
_FREE_REL_EIG = 1e-9
_MAX_ITERATIONS = 30
_STEP_TOL = 1e-12


@dataclass(frozen=True)
class Datum:
    """One datum feature of the scheme.

    Attributes
    ----------
    name : str
    position : (3,) tuple of float, mm, CAD frame
        The feature's nominal (a hole's centre, a surface point).
    directions : tuple of (3,) tuples of float, or of "x", "y", "z"
        The CAD-frame directions it fixes (normalised on construction).
    weight : float
        Relative weight of its residuals (1 by default).
    """

    name: str
    position: tuple[float, float, float]
    directions: tuple[tuple[float, float, float], ...]
    weight: float = 1.0

    def __post_init__(self) -> None:
        if not self.name:
            raise InvalidInput("a datum needs a name")
        p = np.asarray(self.position, dtype=np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise InvalidInput(f"datum {self.name}: position must be three finite numbers")
        dirs = []
        for d in self.directions:
            v = np.asarray(_AXES.get(d, d) if isinstance(d, str) else d, dtype=np.float64)
            if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) < 1e-9:
                raise InvalidInput(f"datum {self.name}: bad direction {d!r}")
            dirs.append(tuple(float(c) for c in v / np.linalg.norm(v)))
        if not dirs:
            raise InvalidInput(f"datum {self.name}: it must fix at least one direction")
        if not (math.isfinite(self.weight) and self.weight > 0):
            raise InvalidInput(f"datum {self.name}: weight must be positive, got {self.weight}")
        object.__setattr__(self, "position", tuple(float(c) for c in p))
        object.__setattr__(self, "directions", tuple(dirs))


@dataclass(frozen=True)
class DatumResidual:
    """What remains at one datum after the alignment, mm, one value per fixed direction."""

    name: str
    residuals_mm: tuple[float, ...]

    @property
    def max_abs_mm(self) -> float:
        return max(abs(r) for r in self.residuals_mm)


@dataclass(frozen=True, eq=False)
class RpsAlignment:
    """The datum alignment.

    Attributes
    ----------
    transform : (4, 4) float64
        T_cad_data.
    residuals : tuple of DatumResidual
        In the datums' order.
    constraints : int
        Directions fixed in all.
    exact : bool
        Six independent constraints: the datums are met exactly.
    free_directions : tuple of str
        Directions the datums leave free (only with ``hold``: kept from it).
    iterations : int
    """

    transform: Transform
    residuals: tuple[DatumResidual, ...]
    constraints: int
    exact: bool
    free_directions: tuple[str, ...]
    iterations: int


@dataclass(frozen=True)
class RpsScheme:
    """A part's datum scheme and how it aligns the part.

    Attributes
    ----------
    datums : tuple of Datum
        Each named as the comparison point that measures it (a hole: its
        centre; a surface point: its point moved by its deviation).
    mode : {"rps", "best_fit_rps"}
        ``rps``: the datums alone (they must fix every direction);
        ``best_fit_rps``: the best fit with the datums held.

    Raises
    ------
    InvalidInput
        An unknown mode, no datums, a name used twice, or (``rps``) a scheme
        that leaves a direction free (named).
    """

    datums: tuple[Datum, ...]
    mode: str = "rps"

    def __post_init__(self) -> None:
        if self.mode not in ALIGNMENTS[1:]:
            raise InvalidInput(f"RPS mode must be one of {ALIGNMENTS[1:]}, got {self.mode!r}")
        ds = tuple(self.datums)
        if not ds:
            raise InvalidInput("an RPS scheme needs datums")
        names = [d.name for d in ds]
        if len(set(names)) != len(names):
            raise InvalidInput(f"an RPS scheme names a datum twice: {names}")
        object.__setattr__(self, "datums", ds)
        # The scheme's own rank, at its nominals: a free direction is a spec error.
        rps_align(ds, np.array([d.position for d in ds]), hold=self.mode == "best_fit_rps")


def rps_align(
    datums: Sequence[Datum],
    measured: npt.ArrayLike,
    *,
    init: npt.ArrayLike | None = None,
    hold: bool = False,
) -> RpsAlignment:
    """The transform that puts each measured datum on its nominal along the directions it fixes.

    Parameters
    ----------
    datums : sequence of Datum
    measured : (K, 3) float64, mm, data frame
        Each datum's measured position, in the datums' order.
    init : (4, 4) float64, optional
        Start (T_cad_data); the identity when not given.
    hold : bool
        Keep ``init`` in the directions the datums leave free (a best fit
        constrained to the RPS); otherwise a free direction is an error.

    Raises
    ------
    InvalidInput
        Mismatched inputs, or (without ``hold``) a scheme that leaves a
        direction free: the message names it.
    """
    ds = tuple(datums)
    if not ds or not all(isinstance(d, Datum) for d in ds):
        raise InvalidInput("rps_align needs a sequence of Datum")
    m = np.asarray(measured, dtype=np.float64)
    if m.shape != (len(ds), 3) or not np.isfinite(m).all():
        raise InvalidInput(f"measured must be ({len(ds)}, 3) finite, got shape {m.shape}")
    T = np.eye(4) if init is None else np.array(init, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidInput("init must be a finite 4x4 transform")
    P = np.array([d.position for d in ds])
    D = np.array([v for d in ds for v in d.directions])
    owner = np.array([i for i, d in enumerate(ds) for _ in d.directions])
    w = np.array([d.weight for d in ds for _ in d.directions])
    c = P.mean(axis=0)
    L = max(float(np.sqrt(np.mean(np.sum((P - c) ** 2, axis=1)))), 1.0)

    def residuals(T: np.ndarray) -> np.ndarray:
        q = m[owner] @ T[:3, :3].T + T[:3, 3]
        return np.einsum("ij,ij->i", D, q - P[owner])

    free: tuple[str, ...] = ()
    iterations = 0
    for _ in range(_MAX_ITERATIONS):
        iterations += 1
        q = m[owner] @ T[:3, :3].T + T[:3, 3] - c
        # d . (omega x q + v) = (q x d) . omega + d . v; omega scaled by L (mm).
        J = np.column_stack([np.cross(q, D) / L, D])
        r = residuals(T)
        H = J.T @ (w[:, None] * J)
        eig, vec = np.linalg.eigh(H)
        free_mask = eig <= _FREE_REL_EIG * max(float(eig[-1]), 1e-300)
        if free_mask.any():
            names = tuple(_name(vec[:, k]) for k in np.flatnonzero(free_mask))
            if not hold:
                raise InvalidInput(
                    f"the datum scheme leaves {', '.join(names)} free "
                    f"({len(D)} directions fixed); add a datum that fixes it"
                )
            free = names
        inv = np.where(free_mask, 0.0, 1.0 / np.where(free_mask, 1.0, eig))
        x = -(vec * inv) @ (vec.T @ (J.T @ (w * r)))  # the least-norm Gauss-Newton step
        omega, v = x[:3] / L, x[3:]
        dT = np.eye(4)
        dT[:3, :3] = _rotation(omega)
        dT[:3, 3] = v + c - dT[:3, :3] @ c
        T = dT @ T
        if np.linalg.norm(x) < _STEP_TOL * max(L, 1.0):
            break
    r = residuals(T)
    out = tuple(
        DatumResidual(d.name, tuple(float(v) for v in r[owner == i])) for i, d in enumerate(ds)
    )
    return RpsAlignment(T, out, len(D), len(D) == 6 and not free, free, iterations)


def _rotation(omega: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: the rotation by ``|omega|`` about ``omega``."""
    th = float(np.linalg.norm(omega))
    if th < 1e-15:
        return np.eye(3)
    k = omega / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * (K @ K)


def _name(u: np.ndarray) -> str:
    a = np.abs(u)
    return " + ".join(_NAMES[i] for i in np.flatnonzero(a >= 0.5 * a.max()))

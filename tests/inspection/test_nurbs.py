"""NURBS geometry: evaluation against the basis's definition, finite differences,
exact conics, and the grid against point evaluation."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from inspection.errors import CadLoadError, InvalidInput
from inspection.nurbs import METHODS, Curve, Surface, basis_flops, evaluation_flops, fit_curve


def _cox_de_boor(i: int, p: int, t: float, knots: np.ndarray) -> float:
    """N_{i,p}(t) straight from the recursive definition (0/0 taken as 0),
    with the last non-empty span closed on the right."""
    if p == 0:
        lo, hi = knots[i], knots[i + 1]
        if lo <= t < hi:
            return 1.0
        last = np.flatnonzero(knots[1:] > knots[:-1]).max()
        return 1.0 if (t == hi and i == last) else 0.0
    out = 0.0
    if knots[i + p] > knots[i]:
        out += (t - knots[i]) / (knots[i + p] - knots[i]) * _cox_de_boor(i, p - 1, t, knots)
    if knots[i + p + 1] > knots[i + 1]:
        out += (
            (knots[i + p + 1] - t)
            / (knots[i + p + 1] - knots[i + 1])
            * _cox_de_boor(i + 1, p - 1, t, knots)
        )
    return out


def _oracle_surface_point(s: Surface, u: float, v: float) -> np.ndarray:
    nu, nv = s.shape
    bu = np.array([_cox_de_boor(i, s.degree_u, u, s.knots_u) for i in range(nu)])
    bv = np.array([_cox_de_boor(j, s.degree_v, v, s.knots_v) for j in range(nv)])
    b = np.outer(bu, bv) * s.weights
    return (b[..., None] * s.control_points).sum((0, 1)) / b.sum()


def _random_surface(rng, p, q, nu, nv, clamped=True):  # type: ignore[no-untyped-def]
    def knots(n, d):  # type: ignore[no-untyped-def]
        if clamped:
            inner = np.sort(rng.uniform(0.0, 1.0, n - d - 1))
            return np.r_[np.zeros(d + 1), inner, np.ones(d + 1)]
        return np.sort(rng.uniform(-1.0, 2.0, n + d + 1))

    gx, gy = np.meshgrid(np.linspace(0, 300, nu), np.linspace(0, 200, nv), indexing="ij")
    cp = np.stack([gx, gy, rng.normal(0, 20, gx.shape)], -1) + rng.normal(0, 5, (nu, nv, 3))
    return Surface(p, q, knots(nu, p), knots(nv, q), cp, rng.uniform(0.4, 2.5, (nu, nv)))


# Degrees up to 3 along v run the grid's fixed four-term contraction (padded);
# (4, 5) runs its general one.
CASES = [
    (3, 3, 8, 7, True),
    (2, 3, 5, 9, True),
    (1, 2, 4, 4, True),
    (3, 2, 9, 6, False),
    (4, 5, 7, 8, True),
]


@pytest.fixture(
    scope="module", params=CASES, ids=lambda c: f"p{c[0]}q{c[1]}-{'cl' if c[4] else 'uncl'}"
)
def surface(request):  # type: ignore[no-untyped-def]
    return _random_surface(np.random.default_rng(hash(request.param) % 2**32), *request.param)


def _params(s: Surface, n: int, rng) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    u = rng.uniform(*s.domain_u, n)
    v = rng.uniform(*s.domain_v, n)
    # The domain's corners and a knot value belong to the domain too.
    u[:3] = [s.domain_u[0], s.domain_u[1], s.knots_u[s.degree_u + 1]]
    v[:3] = [s.domain_v[1], s.domain_v[0], s.knots_v[s.degree_v + 1]]
    return u, v


def test_points_match_the_recursive_definition(surface):  # type: ignore[no-untyped-def]
    u, v = _params(surface, 40, np.random.default_rng(1))
    got = surface.evaluate(u, v)
    want = np.array([_oracle_surface_point(surface, a, b) for a, b in zip(u, v, strict=True)])
    assert np.abs(got - want).max() < 1e-9


def test_first_derivatives_match_finite_differences(surface):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(2)
    h = 1e-6
    lo_u, hi_u = surface.domain_u
    lo_v, hi_v = surface.domain_v
    u = rng.uniform(lo_u + 2 * h, hi_u - 2 * h, 200)
    v = rng.uniform(lo_v + 2 * h, hi_v - 2 * h, 200)
    # Keep the difference inside one knot span, where the surface is smooth.
    far_u = np.min(np.abs(u[:, None] - surface.knots_u[None]), axis=1) > 2 * h
    far_v = np.min(np.abs(v[:, None] - surface.knots_v[None]), axis=1) > 2 * h
    u, v = u[far_u & far_v], v[far_u & far_v]
    _, su, sv = surface.evaluate(u, v, derivatives=1)
    fd_u = (surface.evaluate(u + h, v) - surface.evaluate(u - h, v)) / (2 * h)
    fd_v = (surface.evaluate(u, v + h) - surface.evaluate(u, v - h)) / (2 * h)
    scale = max(np.abs(su).max(), np.abs(sv).max())
    assert np.abs(su - fd_u).max() < 1e-6 * scale
    assert np.abs(sv - fd_v).max() < 1e-6 * scale
    # The derivatives are not all zero: the comparison could fail.
    assert scale > 1.0


def test_second_derivatives_match_finite_differences(surface):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(20)
    h = 1e-6
    u = rng.uniform(surface.domain_u[0] + 0.01, surface.domain_u[1] - 0.01, 300)
    v = rng.uniform(surface.domain_v[0] + 0.01, surface.domain_v[1] - 0.01, 300)
    far_u = np.min(np.abs(u[:, None] - surface.knots_u[None]), axis=1) > 2 * h
    far_v = np.min(np.abs(v[:, None] - surface.knots_v[None]), axis=1) > 2 * h
    u, v = u[far_u & far_v], v[far_u & far_v]
    s, su, sv, suu, suv, svv = surface.evaluate(u, v, derivatives=2)
    first = surface.evaluate(u, v, derivatives=1)
    for a, b in zip((s, su, sv), first, strict=True):
        assert np.abs(a - b).max() < 1e-9 * max(1.0, np.abs(b).max())
    _, su_p, sv_p = surface.evaluate(u + h, v, 1)
    _, su_m, sv_m = surface.evaluate(u - h, v, 1)
    _, _, sv_q = surface.evaluate(u, v + h, 1)
    _, _, sv_r = surface.evaluate(u, v - h, 1)
    scale = max(np.abs(suu).max(), np.abs(svv).max(), np.abs(suv).max())
    assert np.abs(suu - (su_p - su_m) / (2 * h)).max() < 1e-5 * scale
    assert np.abs(suv - (sv_p - sv_m) / (2 * h)).max() < 1e-5 * scale
    assert np.abs(svv - (sv_q - sv_r) / (2 * h)).max() < 1e-5 * scale


def test_grid_evaluation_equals_point_evaluation(surface):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(3)
    us = np.sort(rng.uniform(*surface.domain_u, 23))
    vs = np.sort(rng.uniform(*surface.domain_v, 17))
    us[0], vs[-1] = surface.domain_u[0], surface.domain_v[1]
    grid = surface.evaluate_grid(us, vs, derivatives=1)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    point = surface.evaluate(uu.ravel(), vv.ravel(), derivatives=1)
    for g, e in zip(grid, point, strict=True):
        assert g.shape == (23, 17, 3)
        assert np.abs(g.reshape(-1, 3) - e).max() < 1e-9
    # Points alone are the same points.
    assert np.abs(surface.evaluate_grid(us, vs) - grid[0]).max() < 1e-9


def test_grid_parameters_in_any_order_give_the_same_points(surface):  # type: ignore[no-untyped-def]
    # Unsorted, repeated parameters: a row's runs of one v-span are then short.
    rng = np.random.default_rng(6)
    us = rng.uniform(*surface.domain_u, 9)
    vs = np.r_[rng.uniform(*surface.domain_v, 25), surface.domain_v[::-1], surface.domain_v[1]]
    vs[5] = vs[11]
    grid = surface.evaluate_grid(us, vs, derivatives=1)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    point = surface.evaluate(uu.ravel(), vv.ravel(), derivatives=1)
    for g, e in zip(grid, point, strict=True):
        assert np.abs(g.reshape(-1, 3) - e).max() < 1e-9
    order = np.argsort(vs)
    assert np.abs(surface.evaluate_grid(us, vs[order]) - grid[0][:, order]).max() < 1e-9


def _circle(radius: float) -> Curve:
    """The full circle as a rational quadratic of nine control points (NURBS Book, ex. 7.2)."""
    r = radius
    cp = [[r, 0, 0], [r, r, 0], [0, r, 0], [-r, r, 0], [-r, 0, 0],
          [-r, -r, 0], [0, -r, 0], [r, -r, 0], [r, 0, 0]]  # fmt: skip
    c = math.sqrt(0.5)
    weights = [1, c, 1, c, 1, c, 1, c, 1]
    knots = [0, 0, 0, 0.25, 0.25, 0.5, 0.5, 0.75, 0.75, 1, 1, 1]
    return Curve(2, knots, cp, weights)


def test_rational_quadratic_circle_lies_on_its_radius():
    circle = _circle(125.0)
    t = np.linspace(0, 1, 10_001)
    pts, d1, d2 = circle.evaluate(t, derivatives=2)
    assert np.abs(np.linalg.norm(pts[:, :2], axis=1) - 125.0).max() < 1e-12 * 125
    # |C|^2 is constant: C.C' = 0 and C.C'' = -C'.C'.
    speed2 = np.einsum("ij,ij->i", d1, d1)
    assert np.abs(np.einsum("ij,ij->i", pts, d1)).max() < 1e-12 * 125 * np.sqrt(speed2.max())
    assert np.abs(np.einsum("ij,ij->i", pts, d2) + speed2).max() < 1e-10 * speed2.max()
    # Finite differences of the curve agree with its first derivative.
    h = 1e-6
    tt = np.array([0.1, 0.33, 0.6, 0.9])
    fd = (circle.evaluate(tt + h) - circle.evaluate(tt - h)) / (2 * h)
    assert np.abs(fd - circle.evaluate(tt, 1)[1]).max() < 1e-5 * np.abs(d1).max()


def test_rational_cylinder_lies_on_its_radius_on_grids_and_points():
    circle = _circle(80.0)
    cp = np.stack([circle.control_points, circle.control_points + [0, 0, 250.0]], axis=1)
    w = np.stack([circle.weights, circle.weights], axis=1)
    cylinder = Surface(2, 1, circle.knots, [0, 0, 1, 1], cp, w)
    grid, du, dv = cylinder.evaluate_grid(np.linspace(0, 1, 401), np.linspace(0, 1, 11), 1)
    assert np.abs(np.linalg.norm(grid[..., :2], axis=-1) - 80.0).max() < 1e-12 * 80
    assert np.allclose(dv, [0, 0, 250.0], atol=1e-9)
    assert np.abs(np.einsum("ijk,ijk->ij", grid[..., :2], du[..., :2])).max() < 1e-7
    rng = np.random.default_rng(4)
    pts = cylinder.evaluate(rng.random(1000), rng.random(1000))
    assert np.abs(np.linalg.norm(pts[:, :2], axis=1) - 80.0).max() < 1e-12 * 80


def test_unclamped_knots_evaluate_on_their_domain():
    rng = np.random.default_rng(5)
    knots = np.arange(11.0)  # degree 3, 7 control points: domain [3, 7]
    curve = Curve(3, knots, rng.normal(0, 10, (7, 3)), rng.uniform(0.5, 2, 7))
    assert curve.domain == (3.0, 7.0)
    t = np.linspace(3, 7, 9)
    got = curve.evaluate(t)
    for ti, g in zip(t, got, strict=True):
        b = np.array([_cox_de_boor(i, 3, ti, curve.knots) for i in range(7)]) * curve.weights
        assert np.abs(g - (b[:, None] * curve.control_points).sum(0) / b.sum()).max() < 1e-9
    with pytest.raises(InvalidInput, match=r"domain \[3.0, 7.0\]"):
        curve.evaluate([2.5])


GOOD = dict(degree_u=2, degree_v=2, knots_u=[0, 0, 0, 1, 1, 1], knots_v=[0, 0, 0, 1, 1, 1])


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (dict(knots_u=[0, 0, 0, 1, 1]), "knots_u must have n_control"),
        (dict(knots_u=[0, 0, 1, 0.5, 1, 1]), "non-decreasing"),
        (dict(knots_v=[0, 0, 0, np.nan, 1, 1]), "finite"),
        (dict(knots_u=[1, 1, 1, 1, 1, 1]), "empty parameter domain"),
        (dict(degree_u=0), "degree_u must be an integer >= 1"),
        (dict(degree_v=2.0), "degree_v must be an integer"),
        (dict(degree_u=3, knots_u=[0, 0, 0, 0, 1, 1, 1]), "at least 4 control points"),
        (dict(weights=np.zeros((3, 3))), "strictly positive"),
        (dict(weights=np.ones((3, 2))), r"weights must have shape \(3, 3\)"),
        (dict(control_points=np.zeros((3, 3, 2))), r"shape \(nu, nv, 3\)"),
    ],
)
def test_invalid_surfaces_are_refused_clearly(change, message):  # type: ignore[no-untyped-def]
    args = dict(GOOD, control_points=np.zeros((3, 3, 3)), weights=np.ones((3, 3))) | change
    with pytest.raises(InvalidInput, match=message):
        Surface(**args)


def test_an_interior_knot_beyond_the_degree_is_refused():
    with pytest.raises(InvalidInput, match="repeats an interior knot 3 times"):
        Curve(2, [0, 0, 0, 0.5, 0.5, 0.5, 1, 1, 1], np.zeros((6, 3)))
    # Repeated up to the degree is a corner, which is allowed.
    Curve(2, [0, 0, 0, 0.5, 0.5, 1, 1, 1], np.zeros((5, 3)))


def test_invalid_parameters_are_refused_clearly(surface):  # type: ignore[no-untyped-def]
    lo, hi = surface.domain_u
    with pytest.raises(InvalidInput, match="u must lie in the parameter domain"):
        surface.evaluate([hi + 1e-9], [surface.domain_v[0]])
    with pytest.raises(InvalidInput, match="same length"):
        surface.evaluate([lo, hi], [surface.domain_v[0]])
    with pytest.raises(InvalidInput, match="derivatives must be one of 0..2"):
        surface.evaluate([lo], [surface.domain_v[0]], derivatives=3)
    with pytest.raises(InvalidInput, match="derivatives must be one of 0..1"):
        surface.evaluate_grid([lo], [surface.domain_v[0]], derivatives=2)
    with pytest.raises(InvalidInput, match="vs must be finite"):
        surface.evaluate_grid([lo], [np.inf])


def test_inputs_are_copied_not_shared():
    cp = np.zeros((3, 3, 3))
    s = Surface(control_points=cp, weights=None, **GOOD)
    cp[...] = 5.0
    assert np.all(s.evaluate([0.5], [0.5]) == 0.0)
    with pytest.raises(ValueError):
        s.control_points[0, 0, 0] = 1.0


def test_flop_counts_follow_the_loops():
    # Degree 1, no derivative: left, right and one step of the recursion.
    assert basis_flops(1, 0) == 7
    assert basis_flops(3, 1) > basis_flops(3, 0)
    small = evaluation_flops(3, 3, 10, 10, 12, 1)
    large = evaluation_flops(3, 3, 100, 100, 12, 1)
    # Point by point the work is the same for every point; on a grid the
    # per-line share shrinks as the grid grows.
    assert large.per_point == 100 * small.per_point
    assert large.grid < 100 * small.grid
    assert large.ratio > small.ratio > 1.0
    # One grid point of a bicubic, 4 control columns: both bases, the row's
    # contraction (8 sums of 4 terms per column), 12 sums of 4 terms, the quotient.
    row = 4 * 8 * 4 * 2
    one = 2 * 4 * 12 + 4 + 18
    assert evaluation_flops(3, 3, 1, 1, 4, 1).grid == 2 * basis_flops(3, 1) + row + one
    # Below degree 3 along v the grid runs four terms all the same; above, q + 1.
    low = basis_flops(3, 1) + basis_flops(1, 1) + row + one
    assert evaluation_flops(3, 1, 1, 1, 4, 1).grid == low
    assert evaluation_flops(3, 5, 1, 1, 4, 1).grid - evaluation_flops(3, 3, 1, 1, 4, 1).grid == (
        basis_flops(5, 1) - basis_flops(3, 1) + 2 * 2 * 12
    )
    with pytest.raises(InvalidInput):
        evaluation_flops(3, 3, 0, 10, 12)


# --- fitting curves ----------------------------------------------------------------------

FIT_NOISE_MM = 0.005


def _known_curve(seed: int) -> Curve:
    """A rational cubic space curve of 9 control points, ~300 mm long."""
    rng = np.random.default_rng(seed)
    n = 9
    s = np.linspace(0, 1, n)
    cp = np.stack([300 * s, 40 * np.sin(3 * s) + rng.normal(0, 4, n), 20 * np.cos(2 * s)], -1)
    knots = np.r_[np.zeros(4), np.sort(rng.uniform(0.1, 0.9, n - 4)), np.ones(4)]
    return Curve(3, knots, cp, rng.uniform(0.6, 1.6, n))


@pytest.fixture(scope="module")
def noisy_samples():  # type: ignore[no-untyped-def]
    truth = _known_curve(7)
    rng = np.random.default_rng(8)
    t = np.sort(rng.uniform(0, 1, 150))
    t[0], t[-1] = 0.0, 1.0
    return truth, truth.evaluate(t) + rng.normal(0, FIT_NOISE_MM, (150, 3))


@pytest.fixture(scope="module")
def fits(noisy_samples):  # type: ignore[no-untyped-def]
    truth, x = noisy_samples
    return {m: fit_curve(x, 3, truth.knots, method=m, max_iterations=2000) for m in METHODS}


def _deviation_from(truth: Curve, fitted: Curve) -> np.ndarray:
    """Distances (mm) of dense samples of the truth to the fitted curve."""
    t = np.linspace(*truth.domain, 2000)
    pts = truth.evaluate(t)
    return np.linalg.norm(fitted.evaluate(fitted.project(pts, t)) - pts, axis=1)


@pytest.mark.parametrize("method", METHODS)
def test_a_fit_recovers_a_known_curve_from_noisy_samples(fits, noisy_samples, method):  # type: ignore[no-untyped-def]
    truth, x = noisy_samples
    fit = fits[method]
    assert fit.converged, fit.stop_reason
    # Orthogonal residuals of 3-D noise: about sqrt(2) sigma.
    assert 0.8 * math.sqrt(2) * FIT_NOISE_MM < fit.rms_mm < 1.2 * math.sqrt(2) * FIT_NOISE_MM
    # The curve itself is closer to the truth than the noise of its samples.
    assert _deviation_from(truth, fit.curve).max() < 2 * FIT_NOISE_MM
    # A start with unit weights fits far worse: the fit did the work.
    start = fit_curve(x, 3, truth.knots, method=method, max_iterations=1)
    assert start.rms_mm > 3 * fit.rms_mm
    # The cost never rises.
    assert np.all(np.diff(fit.cost_history) < 0)


def test_all_methods_reach_the_same_minimum(fits):  # type: ignore[no-untyped-def]
    costs = np.array([f.cost for f in fits.values()])
    assert np.ptp(costs) < 1e-6 * costs.min()


def test_splitting_takes_the_same_steps_as_the_normal_equations(fits):  # type: ignore[no-untyped-def]
    a, b = fits["normal"], fits["split"]
    k = min(len(a.cost_history), len(b.cost_history), 30)
    assert np.allclose(a.cost_history[:k], b.cost_history[:k], rtol=1e-8, atol=0)


def test_newton_hessian_matches_finite_differences_of_the_gradient():
    from inspection.nurbs import fit as fitmod

    rng = np.random.default_rng(9)
    n, m = 6, 12
    knots = np.r_[np.zeros(4), [1 / 3, 2 / 3], np.ones(4)]
    d2 = np.diff(np.eye(n), 2, axis=0)
    prob = fitmod._Problem(3, knots, rng.normal(0, 10, (m, 3)), 1e-3, 1e-2, d2.T @ d2)

    def unpack(v):  # type: ignore[no-untyped-def]
        return fitmod._state(prob, v[:m], v[m : m + 3 * n].reshape(3, n).T, v[m + 3 * n :], 2)

    def gradient(v):  # type: ignore[no-untyped-def]
        g_t, g_y, *_ = fitmod._gradient_and_blocks(prob, unpack(v))
        return np.r_[g_t, g_y]

    v0 = np.r_[
        np.sort(rng.uniform(0.05, 0.95, m)), rng.normal(0, 10, 3 * n), rng.uniform(0.6, 1.6, n)
    ]
    s0 = unpack(v0)
    _, _, D, B, E = fitmod._gradient_and_blocks(prob, s0)
    fitmod._second_order(prob, s0, D, B, E)
    H = np.block([[np.diag(D), B], [B.T, E]])
    h = 1e-6
    fd = np.array(
        [(gradient(v0 + h * e) - gradient(v0 - h * e)) / (2 * h) for e in np.eye(v0.size)]
    )
    assert np.abs(H - fd).max() < 1e-6 * np.abs(H).max()


def test_foot_points_are_orthogonal(noisy_samples):  # type: ignore[no-untyped-def]
    truth, x = noisy_samples
    t = truth.project(x, np.linspace(0, 1, len(x)))
    c, d1 = truth.evaluate(t, derivatives=1)
    inside = (t > 0) & (t < 1)
    cos = np.einsum("ij,ij->i", c - x, d1)[inside] / np.linalg.norm(d1[inside], axis=1)
    assert np.abs(cos).max() < 1e-9


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(method="lm"), "method must be one of"),
        (dict(points=np.zeros((10, 2))), r"finite \(m, 3\)"),
        (dict(points=np.full((20, 3), np.nan)), r"finite \(m, 3\)"),
        (dict(points=np.zeros((5, 3))), "need at least 9 points"),
        (dict(points=np.zeros((20, 3))), "must not all coincide"),
        (dict(weight_penalty=0.0), "weight_penalty"),
        (dict(max_iterations=0), "max_iterations"),
        (dict(knots=np.r_[np.zeros(4), [0.5, 0.4], np.ones(4)]), "non-decreasing"),
    ],
)
def test_invalid_fits_are_refused_clearly(noisy_samples, kwargs, message):  # type: ignore[no-untyped-def]
    truth, x = noisy_samples
    args = dict(points=x, degree=3, knots=truth.knots) | kwargs
    with pytest.raises(InvalidInput, match=message):
        fit_curve(**args)


# --- closest points and the exact surface ------------------------------------------------


@pytest.fixture(scope="module")
def panel():  # type: ignore[no-untyped-def]
    """A crowned 300 x 200 mm rational bicubic panel."""
    rng = np.random.default_rng(11)
    nu, nv = 7, 6
    gx, gy = np.meshgrid(np.linspace(-150, 150, nu), np.linspace(-100, 100, nv), indexing="ij")
    crown = 25.0 * (1 - (gx / 150) ** 2) * (1 - 0.5 * (gy / 100) ** 2) + rng.normal(0, 2, gx.shape)
    knots_u = np.r_[np.zeros(4), [0.3, 0.55, 0.8], np.ones(4)]
    knots_v = np.r_[np.zeros(4), [0.4, 0.7], np.ones(4)]
    cp = np.stack([gx, gy, crown], -1)
    return Surface(3, 3, knots_u, knots_v, cp, rng.uniform(0.7, 1.4, (nu, nv)))


@pytest.fixture(scope="module")
def dense(panel):  # type: ignore[no-untyped-def]
    """The oracle's samples: a 700 x 700 parameter grid, and half the longest
    diagonal of its cells (mm): every surface point is that close to a sample."""
    us = np.linspace(0, 1, 700)
    grid = panel.evaluate_grid(us, us)
    diag = max(
        np.linalg.norm(grid[1:, 1:] - grid[:-1, :-1], axis=-1).max(),
        np.linalg.norm(grid[1:, :-1] - grid[:-1, 1:], axis=-1).max(),
    )
    uv = np.stack(np.meshgrid(us, us, indexing="ij"), -1).reshape(-1, 2)
    return grid.reshape(-1, 3), uv, diag / 2


def _near_points(surface: Surface, n: int, seed: int, lo=0.0, hi=1.0):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    uv = rng.uniform(lo, hi, (n, 2))
    s, su, sv = surface.evaluate(uv[:, 0], uv[:, 1], 1)
    normal = np.cross(su, sv)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return s + rng.uniform(-3, 3, n)[:, None] * normal + rng.normal(0, 1, (n, 3))


def _oracle(x: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index and distance of the nearest dense sample of each point (brute force)."""
    idx, dist = [], []
    for q in x:
        d = np.linalg.norm(pts - q, axis=1)
        idx.append(int(d.argmin()))
        dist.append(float(d.min()))
    return np.array(idx), np.array(dist)


def test_closest_points_against_a_dense_oracle(panel, dense):  # type: ignore[no-untyped-def]
    from inspection.nurbs.closest import closest_points

    pts, _, half_cell = dense
    x = _near_points(panel, 40, 12, 0.05, 0.95)
    got = closest_points(panel, x)
    assert got.converged.all()
    j, d_oracle = _oracle(x, pts)
    d = np.linalg.norm(x - got.points, axis=1)
    # Never farther than the nearest of 490,000 samples, and nearer only by
    # what the samples' spacing allows.
    assert np.all(d <= d_oracle + 1e-9)
    assert np.all(d_oracle <= np.hypot(d, half_cell) + 1e-9)
    assert np.linalg.norm(got.points - pts[j], axis=1).max() < 2 * half_cell
    # The foot point is orthogonal and the signed distance is along the normal.
    _, su, sv = panel.evaluate(got.params[:, 0], got.params[:, 1], 1)
    r = x - got.points
    assert np.abs(np.einsum("ij,ij->i", r, su)).max() < 1e-8 * np.abs(su).max()
    assert np.abs(np.einsum("ij,ij->i", r, sv)).max() < 1e-8 * np.abs(sv).max()
    assert np.allclose(np.abs(got.distances), d, atol=1e-9)


def test_closest_points_far_off_the_surface_converge(panel):  # type: ignore[no-untyped-def]
    from inspection.nurbs.closest import closest_points

    rng = np.random.default_rng(17)
    uv = rng.uniform(0.1, 0.9, (300, 2))
    s, su, sv = panel.evaluate(uv[:, 0], uv[:, 1], 1)
    normal = np.cross(su, sv)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    off = rng.choice([-20.0, 20.0], 300)  # both sides, the concave one too
    got = closest_points(panel, s + off[:, None] * normal)
    assert got.converged.all()
    assert np.allclose(got.distances, off, atol=1e-9)
    assert np.allclose(got.params, uv, atol=1e-9)


def test_trimming_is_respected(panel, dense):  # type: ignore[no-untyped-def]
    from inspection.nurbs.closest import Trim, closest_points

    pts, uv, half_cell = dense
    # A pentagon: the panel with a corner cut off and its edges pulled in.
    trim = Trim(np.array([[0.1, 0.1], [0.9, 0.1], [0.9, 0.55], [0.55, 0.9], [0.1, 0.9]]))
    x = _near_points(panel, 60, 13)
    got = closest_points(panel, x, trim=trim)
    free = closest_points(panel, x)
    outside = ~trim.contains(free.params)
    assert 10 < outside.sum() < 50  # some feet fall outside, some inside
    assert np.array_equal(got.on_boundary, outside)
    # Inside feet are the untrimmed ones; every foot lies in (or on) the polygon.
    assert np.allclose(got.points[~outside], free.points[~outside], atol=1e-9)
    shrunk = Trim(0.5 + (trim.polygon - 0.5) * (1 + 1e-6))
    assert shrunk.contains(got.params).all()
    # Against the dense samples inside the trim: never farther than the nearest.
    inside = trim.contains(uv)
    j, d_oracle = _oracle(x, pts[inside])
    d = np.linalg.norm(x - got.points, axis=1)
    assert np.all(d <= d_oracle + 1e-9)
    # A foot on the boundary has an inside sample within a cell's diagonal.
    assert np.all(d_oracle <= d + 2 * half_cell + 1e-9)


def test_deviations_to_the_exact_surface_beat_the_tessellation(panel):  # type: ignore[no-untyped-def]
    from inspection.grid import GridTree
    from inspection.nurbs.model import ExactTree, tessellate

    face = tessellate(panel, 31, 21)  # 10 mm cells: chords of tens of micrometres
    tree = GridTree.build(face.cad, spacing_mm=2.0, band_mm=4.0)
    rng = np.random.default_rng(14)
    uv = rng.uniform(0.02, 0.98, (500, 2))
    s, su, sv = panel.evaluate(uv[:, 0], uv[:, 1], 1)
    normal = np.cross(su, sv)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    truth = rng.uniform(-0.3, 0.3, 500)
    x = s + truth[:, None] * normal
    mesh_error = np.abs(tree.query(x).distances - truth)
    exact = ExactTree(tree, face).query(x)
    assert mesh_error.max() > 1e-3  # the chords are visible
    assert np.abs(exact.distances - truth).max() < 1e-9
    assert np.allclose(exact.points, s, atol=1e-8)


def test_an_exact_tree_refuses_another_tessellation(panel):  # type: ignore[no-untyped-def]
    from inspection.grid import GridTree
    from inspection.nurbs.model import ExactTree, tessellate

    coarse, fine = tessellate(panel, 6, 5), tessellate(panel, 7, 5)
    with pytest.raises(InvalidInput, match="not built on this model"):
        ExactTree(GridTree.build(coarse.cad, spacing_mm=5.0, band_mm=5.0), fine)


def test_invalid_trims_are_refused(panel):  # type: ignore[no-untyped-def]
    from inspection.nurbs.closest import Trim, closest_points

    with pytest.raises(InvalidInput, match="leaves the parameter domain"):
        closest_points(panel, np.zeros((1, 3)), trim=Trim(np.array([[0, 0], [1.5, 0], [0, 1.0]])))
    with pytest.raises(InvalidInput, match=r"shape \(k >= 3, 2\)"):
        Trim(np.zeros((2, 2)))
    with pytest.raises(InvalidInput, match="enclose an area"):
        Trim(np.array([[0, 0], [1, 1], [2, 2.0]]))


# --- reading NURBS CAD -------------------------------------------------------------------

HAS_RHINO = importlib.util.find_spec("rhino3dm") is not None


def _sample_grid(s: Surface) -> np.ndarray:
    return s.evaluate_grid(np.linspace(*s.domain_u, 15), np.linspace(*s.domain_v, 11))


def test_step_surfaces_round_trip(tmp_path, panel):  # type: ignore[no-untyped-def]
    from inspection.nurbs.step import read_step_surfaces, write_step_surfaces

    other = _random_surface(np.random.default_rng(21), 2, 3, 5, 6)
    path = write_step_surfaces(tmp_path / "panel.step", [panel, other])
    back = read_step_surfaces(path, scale=2.0)
    assert len(back) == 2
    for want, got in zip([panel, other], back, strict=True):
        assert (got.degree_u, got.degree_v) == (want.degree_u, want.degree_v)
        assert np.array_equal(got.knots_u, want.knots_u)
        assert np.array_equal(got.weights, want.weights)
        assert np.abs(_sample_grid(got) - 2.0 * _sample_grid(want)).max() < 1e-9


def test_the_b_spline_face_of_a_real_step_file_lies_on_its_part(shared_cad):  # type: ignore[no-untyped-def]
    import trimesh

    from inspection.nurbs.step import read_step_surfaces

    (surface,) = read_step_surfaces(shared_cad("featuretype.STEP"))
    assert (surface.degree_u, surface.degree_v) == (3, 1)
    stl = trimesh.load(shared_cad("featuretype.STL"))
    pts = _sample_grid(surface).reshape(-1, 3)
    _, dist, _ = trimesh.proximity.closest_point(stl, pts)
    # The STL is a tessellation of the same part: within its chord error.
    assert dist.max() < 0.01 * float(np.max(stl.extents))


def test_bad_step_files_are_refused_clearly(tmp_path):  # type: ignore[no-untyped-def]
    from inspection.nurbs.step import read_step_surfaces

    (tmp_path / "empty.step").write_text("ISO-10303-21;\nHEADER;\nENDSEC;\n")
    with pytest.raises(CadLoadError, match="no DATA section"):
        read_step_surfaces(tmp_path / "empty.step")
    with pytest.raises(CadLoadError, match="missing.step"):
        read_step_surfaces(tmp_path / "missing.step")
    bad = (
        "ISO-10303-21;\nDATA;\n#1 = CARTESIAN_POINT('',(0.,0.,0.));\n"
        "#2 = B_SPLINE_SURFACE_WITH_KNOTS('',1,1,((#1,#1),(#1,#1)),.UNSPECIFIED.,.F.,.F.,.F.,"
        "(2,2),(2,1),(0.,1.),(0.,1.),.UNSPECIFIED.);\nENDSEC;\nEND-ISO-10303-21;\n"
    )
    (tmp_path / "bad.step").write_text(bad)
    with pytest.raises(CadLoadError, match=r"#2: knots_v must have n_control"):
        read_step_surfaces(tmp_path / "bad.step")


@pytest.mark.skipif(not HAS_RHINO, reason="rhino3dm (extra 'step') is not installed")
def test_3dm_surfaces_round_trip_and_agree_with_rhino(tmp_path, panel):  # type: ignore[no-untyped-def]
    import rhino3dm

    from inspection.nurbs.rhino import read_3dm_surfaces, write_3dm_surfaces

    path = write_3dm_surfaces(tmp_path / "panel.3dm", [panel])
    (back,) = read_3dm_surfaces(path)
    assert np.abs(_sample_grid(back) - _sample_grid(panel)).max() < 1e-9
    # Rhino's own evaluation of the surface it read agrees with ours.
    (obj,) = rhino3dm.File3dm.Read(str(path)).Objects
    uv = np.random.default_rng(22).random((20, 2))
    theirs = np.array([[q.X, q.Y, q.Z] for q in (obj.Geometry.PointAt(u, v) for u, v in uv)])
    assert np.abs(back.evaluate(uv[:, 0], uv[:, 1]) - theirs).max() < 1e-9
    with pytest.raises(CadLoadError, match="no such file"):
        read_3dm_surfaces(tmp_path / "missing.3dm")


TRIMMED_STEP = """ISO-10303-21;
HEADER;
FILE_SCHEMA(('AUTOMOTIVE_DESIGN'));
ENDSEC;
DATA;
#1 = CARTESIAN_POINT('',(0.,0.,0.));
#2 = CARTESIAN_POINT('',(0.,100.,0.));
#3 = CARTESIAN_POINT('',(100.,0.,0.));
#4 = CARTESIAN_POINT('',(100.,100.,0.));
#5 = B_SPLINE_SURFACE_WITH_KNOTS('',1,1,((#1,#2),(#3,#4)),.UNSPECIFIED.,.F.,.F.,.F.,
  (2,2),(2,2),(0.,1.),(0.,1.),.UNSPECIFIED.);
#10 = CARTESIAN_POINT('',(10.,10.,0.));
#11 = CARTESIAN_POINT('',(90.,10.,0.));
#12 = CARTESIAN_POINT('',(10.,90.,0.));
#13 = VERTEX_POINT('',#10);
#14 = VERTEX_POINT('',#11);
#15 = VERTEX_POINT('',#12);
#20 = DIRECTION('',(1.,0.,0.));
#21 = VECTOR('',#20,80.);
#22 = LINE('',#10,#21);
#23 = EDGE_CURVE('',#13,#14,#22,.T.);
#30 = DIRECTION('',(0.,0.,1.));
#31 = AXIS2_PLACEMENT_3D('',#10,#30,#20);
#32 = CIRCLE('',#31,80.);
#33 = EDGE_CURVE('',#14,#15,#32,.T.);
#40 = B_SPLINE_CURVE_WITH_KNOTS('',1,(#10,#12),.UNSPECIFIED.,.F.,.F.,(2,2),(0.,1.),.UNSPECIFIED.);
#41 = EDGE_CURVE('',#13,#15,#40,.T.);
#50 = ORIENTED_EDGE('',*,*,#23,.T.);
#51 = ORIENTED_EDGE('',*,*,#33,.T.);
#52 = ORIENTED_EDGE('',*,*,#41,.F.);
#60 = EDGE_LOOP('',(#50,#51,#52));
#61 = FACE_OUTER_BOUND('',#60,.T.);
#70 = CARTESIAN_POINT('',(40.,40.,0.));
#71 = CARTESIAN_POINT('',(50.,40.,0.));
#72 = VERTEX_POINT('',#71);
#73 = AXIS2_PLACEMENT_3D('',#70,#30,#20);
#74 = CIRCLE('',#73,10.);
#75 = EDGE_CURVE('',#72,#72,#74,.T.);
#76 = ORIENTED_EDGE('',*,*,#75,.F.);
#77 = EDGE_LOOP('',(#76));
#78 = FACE_BOUND('',#77,.T.);
#62 = ADVANCED_FACE('',(#61,#78),#5,.T.);
ENDSEC;
END-ISO-10303-21;
"""


def test_a_step_face_brings_its_trim(tmp_path):  # type: ignore[no-untyped-def]
    from inspection.nurbs.step import read_step_faces

    # A 100 x 100 mm square patch trimmed to a quarter disc of radius 80 mm
    # about (10, 10) (a line, an arc and a reversed B-spline edge), with a
    # hole of radius 10 mm about (40, 40) (one closed circular edge).
    (tmp_path / "quarter.step").write_text(TRIMMED_STEP)
    ((surface, trim),) = read_step_faces(tmp_path / "quarter.step")
    uv = trim.polygon
    # Every boundary vertex lies on one of the three edges (u, v = x, y / 100).
    on_line = (np.abs(uv[:, 1] - 0.1) < 1e-9) | (np.abs(uv[:, 0] - 0.1) < 1e-9)
    on_arc = np.abs(np.hypot(uv[:, 0] - 0.1, uv[:, 1] - 0.1) - 0.8) < 1e-9
    assert np.all(on_line | on_arc) and on_arc.sum() > 10
    inside = trim.contains(np.array([[0.2, 0.2], [0.6, 0.6], [0.85, 0.85], [0.05, 0.5]]))
    assert inside.tolist() == [True, True, False, False]
    (hole,) = trim.holes
    assert np.abs(np.hypot(hole[:, 0] - 0.4, hole[:, 1] - 0.4) - 0.1).max() < 1e-9
    assert trim.contains(np.array([[0.4, 0.4], [0.4, 0.52]])).tolist() == [False, True]
    # The face measures as trimmed: a point above the cut-away corner finds the arc.
    from inspection.nurbs.closest import closest_points

    got = closest_points(surface, np.array([[95.0, 95.0, 1.0], [42.0, 40.0, 1.0]]), trim=trim)
    assert got.on_boundary.all()
    assert np.hypot(*(got.points[0, :2] - 10.0)) == pytest.approx(80.0, abs=1e-6)
    # Above the hole: the closest point of the face is on the hole's rim, 8 mm
    # across and 1 mm down (to the polygon's 1 um chords).
    assert np.hypot(*(got.points[1, :2] - 40.0)) == pytest.approx(10.0, abs=2e-3)
    assert np.linalg.norm(got.points[1] - [42.0, 40.0, 1.0]) == pytest.approx(65**0.5, abs=2e-3)


def test_the_real_b_spline_face_is_bounded_by_its_domain(shared_cad):  # type: ignore[no-untyped-def]
    from inspection.nurbs.step import read_step_faces

    ((surface, trim),) = read_step_faces(shared_cad("featuretype.STEP"), scale=60.0)
    # Its four edges are the iso-lines at the ends of the domain.
    lo = [surface.domain_u[0], surface.domain_v[0]]
    hi = [surface.domain_u[1], surface.domain_v[1]]
    assert np.allclose(trim.polygon.min(axis=0), lo, atol=1e-6)
    assert np.allclose(trim.polygon.max(axis=0), hi, atol=1e-6)


def test_a_measured_edge_deviates_from_its_nominal_as_it_was_made(noisy_samples):  # type: ignore[no-untyped-def]
    from inspection.nurbs import deviation_along

    nominal, _ = noisy_samples
    # The edge as made: the nominal moved 0.2 mm along z; measured with noise.
    made = Curve(nominal.degree, nominal.knots, nominal.control_points + [0, 0, 0.2],
                 nominal.weights)  # fmt: skip
    rng = np.random.default_rng(15)
    t = np.sort(rng.uniform(0, 1, 150))
    t[0], t[-1] = 0.0, 1.0
    x = made.evaluate(t) + rng.normal(0, FIT_NOISE_MM, (150, 3))
    fitted = fit_curve(x, 3, nominal.knots, method="vp-gn").curve
    dev = deviation_along(fitted, nominal, samples=100)
    assert dev.distances.shape == (100,)
    # The nominal runs nearly across z (|t_z| < 0.15): the deviation is about the shift.
    inner = slice(5, -5)
    assert np.abs(dev.vectors[inner, 2] - 0.2).max() < 3 * FIT_NOISE_MM
    assert np.abs(dev.distances[inner] - 0.2).max() < 3 * FIT_NOISE_MM
    with pytest.raises(InvalidInput, match="samples must be an integer >= 2"):
        deviation_along(fitted, nominal, samples=1)


def test_a_part_of_several_trimmed_faces_measures_to_each_exact_face(tmp_path, panel):  # type: ignore[no-untyped-def]
    from inspection.grid import GridTree
    from inspection.nurbs.closest import Trim
    from inspection.nurbs.model import ExactTree, tessellate_faces
    from inspection.nurbs.step import read_step_faces

    # The quarter disc with its hole (from STEP) beside the crowned panel.
    (tmp_path / "quarter.step").write_text(TRIMMED_STEP)
    ((disc, disc_trim),) = read_step_faces(tmp_path / "quarter.step")
    moved = Surface(3, 3, panel.knots_u, panel.knots_v, panel.control_points + [300.0, 0, 0],
                    panel.weights)  # fmt: skip
    half = Trim(np.array([[0, 0], [0.5, 0], [0.5, 1], [0, 1.0]]))
    model = tessellate_faces([(disc, disc_trim), (moved, half)], cell_mm=4.0)
    assert set(np.unique(model.triangle_face)) == {0, 1}
    exact = ExactTree(GridTree.build(model.cad, spacing_mm=2.0, band_mm=4.0), model)
    rng = np.random.default_rng(16)
    # On the disc, 0.5 mm above it, away from its boundary.
    r, a = rng.uniform(12, 70, 200), rng.uniform(0.05, np.pi / 2 - 0.05, 200)
    on_disc = np.stack([10 + r * np.cos(a), 10 + r * np.sin(a), np.full(200, 0.5)], 1)
    on_disc = on_disc[np.hypot(on_disc[:, 0] - 40, on_disc[:, 1] - 40) > 12]
    # On the panel's kept half, along its normal.
    uv = rng.uniform([0.05, 0.05], [0.45, 0.95], (200, 2))
    s, su, sv = moved.evaluate(uv[:, 0], uv[:, 1], 1)
    normal = np.cross(su, sv)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    truth = rng.uniform(-0.3, 0.3, 200)
    got = exact.query(np.concatenate([on_disc, s + truth[:, None] * normal]))
    n = len(on_disc)
    assert np.allclose(np.abs(got.distances[:n]), 0.5, atol=1e-9)
    assert np.abs(got.distances[n:] - truth).max() < 1e-9

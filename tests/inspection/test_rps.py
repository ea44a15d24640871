"""RPS (3-2-1) alignment: exact where 3-2-1, least squares beyond, free directions named."""

from __future__ import annotations

import numpy as np
import pytest

from inspection.alignment.rps import Datum, rps_align
from inspection.errors import InvalidInput
from inspection.rig import belt_pose
from inspection.transforms import apply

# A hole fixing x and y, a slot fixing y, three surface points fixing z (panel frame, mm).
SCHEME = (
    Datum("H1", (113.0, 71.5, 35.0), ("x", "y")),
    Datum("S2", (-133.0, 78.0, 34.0), ("y",)),
    Datum("Z1", (150.0, -90.0, 31.0), ("z",)),
    Datum("Z2", (-150.0, -90.0, 31.0), ("z",)),
    Datum("Z3", (0.0, 100.0, 35.0), ("z",)),
)


def nominals(scheme) -> np.ndarray:
    return np.array([d.position for d in scheme])


@pytest.fixture
def T_true() -> np.ndarray:
    T = belt_pose(40.0, -25.0, 33.0)
    T[:3, 3] += (0.0, 0.0, 12.0)
    return T  # T_cad_data


def test_a_3_2_1_scheme_is_met_exactly(T_true):
    measured = apply(np.linalg.inv(T_true), nominals(SCHEME))
    rps = rps_align(SCHEME, measured)
    assert rps.exact and rps.constraints == 6 and rps.free_directions == ()
    np.testing.assert_allclose(rps.transform, T_true, atol=1e-9)
    assert max(r.max_abs_mm for r in rps.residuals) < 1e-9


def test_the_3_2_1_scheme_puts_its_datums_where_they_say_and_leaves_the_rest(T_true):
    """Off-nominal features: each datum is met exactly, and a point no datum fixes
    carries the features' deviation."""
    rng = np.random.default_rng(0)
    measured = apply(np.linalg.inv(T_true), nominals(SCHEME) + rng.normal(0, 0.3, (5, 3)))
    rps = rps_align(SCHEME, measured)
    assert rps.exact
    assert max(r.max_abs_mm for r in rps.residuals) < 1e-9
    assert not np.allclose(rps.transform, T_true, atol=1e-3)


def test_more_datums_give_least_squares_residuals_and_weights_count(T_true):
    scheme = (*SCHEME, Datum("X2", (-150.0, 0.0, 33.0), ("x",)))
    truth = nominals(scheme)
    off = truth.copy()
    off[-1, 0] += 0.4  # the extra datum disagrees with the hole by 0.4 mm in x
    measured = apply(np.linalg.inv(T_true), off)
    even = rps_align(scheme, measured)
    assert not even.exact and even.constraints == 7
    r_h1, r_x2 = even.residuals[0].residuals_mm[0], even.residuals[-1].residuals_mm[0]
    assert abs(r_h1) > 0.05 and abs(r_x2) > 0.05
    assert abs(r_h1 - r_x2 + 0.4) < 0.05 or abs(r_x2 - r_h1 - 0.4) < 0.05
    heavy = rps_align((*scheme[:-1], Datum("X2", scheme[-1].position, ("x",), 100.0)), measured)
    assert abs(heavy.residuals[-1].residuals_mm[0]) < abs(r_x2) / 10


@pytest.mark.parametrize(
    "drop, free",
    [("S2", "rotation about z"), ("Z3", "rotation about x"), ("H1", "translation along x")],
)
def test_an_under_determined_scheme_names_the_free_direction(T_true, drop, free):
    scheme = tuple(d for d in SCHEME if d.name != drop)
    measured = apply(np.linalg.inv(T_true), nominals(scheme))
    with pytest.raises(InvalidInput, match=free):
        rps_align(scheme, measured)


def test_held_to_a_best_fit_the_free_directions_stay(T_true):
    scheme = tuple(d for d in SCHEME if d.name != "S2")  # rotation about z left free
    measured = apply(np.linalg.inv(T_true), nominals(scheme) + [0.0, 0.0, 0.2])
    best_fit = T_true.copy()
    rps = rps_align(scheme, measured, init=best_fit, hold=True)
    assert rps.free_directions and "rotation about z" in rps.free_directions[0]
    assert max(r.max_abs_mm for r in rps.residuals) < 1e-9
    # Only z moved: the turn about z and the in-plane place are the best fit's.
    np.testing.assert_allclose(rps.transform[:2, :], best_fit[:2, :], atol=1e-9)
    assert abs(rps.transform[2, 3] - best_fit[2, 3] + 0.2) < 1e-9


def test_bad_input_is_refused():
    with pytest.raises(InvalidInput, match="measured"):
        rps_align(SCHEME, np.zeros((4, 3)))
    with pytest.raises(InvalidInput, match="direction"):
        Datum("D", (0, 0, 0), ((0.0, 0.0, 0.0),))
    with pytest.raises(InvalidInput, match="weight"):
        Datum("D", (0, 0, 0), ("x",), weight=0.0)

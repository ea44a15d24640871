"""The rigid-transform helper."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from inspection.transforms import apply


def _random_transform(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-100, 100, 3)
    return T


def test_apply_maps_points_and_composes():
    rng = np.random.default_rng(1)
    T_ab, T_bc = _random_transform(rng), _random_transform(rng)
    p = rng.uniform(-300, 300, (50, 3))
    homogeneous = (T_ab @ np.column_stack([p, np.ones(len(p))]).T).T[:, :3]
    np.testing.assert_allclose(apply(T_ab, p), homogeneous, atol=1e-10)
    np.testing.assert_allclose(apply(T_ab, apply(T_bc, p)), apply(T_ab @ T_bc, p), atol=1e-9)
    np.testing.assert_array_equal(apply(np.eye(4), p), p)
    # The very expression the code base used inline, bit for bit.
    assert apply(T_ab, p).tobytes() == (p @ T_ab[:3, :3].T + T_ab[:3, 3]).tobytes()

"""The fit's compiled kernels: robust loss, residuals, normal equations, damped step, pose update.

The cost of the residuals ``r_i(T)`` is

    E(T) = sum_i v_i sigma^2 rho(r_i / sigma) / sum_i v_i

with ``v_i`` the input weights, ``rho`` an M-estimator (normalised so that
``sigma^2 rho(r / sigma) ~ r^2 / 2`` for small residuals) and ``sigma`` a
robust scale. Its IRLS weights are ``w_i = v_i psi(x) / x`` with ``x = r_i /
sigma``. For every loss here ``psi(x) / x`` does not increase with ``|x|``,
so the half-quadratic IRLS surrogate majorises the robust cost (Huber's and
Black-Rangarajan's construction), and ``sigma^2 rho(r / sigma)`` does not
decrease with ``sigma``, so narrowing the scale never raises the cost.

Every loop is serial and runs in a fixed order (no parallel reductions, no
BLAS): the same input gives bit-identical output.
"""

from __future__ import annotations

import numba
import numpy as np

from .._linalg import cholesky_solve

# Loss ids for the numba kernels and their tuning constants for unit scale:
# the usual 95 % asymptotic efficiency constants under Gaussian noise.
LOSSES: dict[str, tuple[int, float]] = {
    "l2": (0, 1.0),
    "huber": (1, 1.345),
    "tukey": (2, 4.685),
    "cauchy": (3, 2.3849),
    "welsch": (4, 2.9846),
}


@numba.njit(cache=True)
def rho_weight(r: float, sigma: float, loss: int, c: float) -> tuple[float, float]:
    """``sigma^2 rho(r / sigma)`` and the IRLS weight ``psi(x) / x``."""
    x = r / sigma
    if loss == 0:
        return 0.5 * r * r, 1.0
    if loss == 1:  # Huber
        a = abs(x)
        if a <= c:
            return 0.5 * r * r, 1.0
        return sigma * sigma * c * (a - 0.5 * c), c / a
    u = (x / c) * (x / c)
    if loss == 2:  # Tukey's biweight
        if u >= 1.0:
            return sigma * sigma * c * c / 6.0, 0.0
        v = 1.0 - u
        return sigma * sigma * c * c / 6.0 * (1.0 - v * v * v), v * v
    if loss == 3:  # Cauchy
        return sigma * sigma * c * c * 0.5 * np.log1p(u), 1.0 / (1.0 + u)
    # Welsch
    e = np.exp(-u)
    return sigma * sigma * c * c * 0.5 * (1.0 - e), e


@numba.njit(cache=True)
def transform_points(R: np.ndarray, t: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``R p + t`` for each row ``p`` of ``P`` (N, 3)."""
    n = P.shape[0]
    X = np.empty((n, 3))
    for i in range(n):
        for k in range(3):
            X[i, k] = R[k, 0] * P[i, 0] + R[k, 1] * P[i, 1] + R[k, 2] * P[i, 2] + t[k]
    return X


@numba.njit(cache=True)
def plane_residuals(X: np.ndarray, Q: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Point-to-plane residuals ``n_i . (x_i - q_i)`` to each closest face's plane."""
    n = X.shape[0]
    r = np.empty(n)
    for i in range(n):
        r[i] = (
            N[i, 0] * (X[i, 0] - Q[i, 0])
            + N[i, 1] * (X[i, 1] - Q[i, 1])
            + N[i, 2] * (X[i, 2] - Q[i, 2])
        )
    return r


@numba.njit(cache=True)
def distance_residuals(
    X: np.ndarray, Q: np.ndarray, N: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances and their gradients ``(x - q) / d`` (the face normal on the face)."""
    n = X.shape[0]
    r = np.empty(n)
    U = np.empty((n, 3))
    for i in range(n):
        di = d[i]
        r[i] = di
        ex = X[i, 0] - Q[i, 0]
        ey = X[i, 1] - Q[i, 1]
        ez = X[i, 2] - Q[i, 2]
        along = N[i, 0] * ex + N[i, 1] * ey + N[i, 2] * ez
        e2 = ex * ex + ey * ey + ez * ez
        # Off the face's interior the foot is on an edge or corner: the
        # distance grows along x - q, not along the face normal.
        if e2 > 1e-24 and e2 - along * along > 1e-6 * e2:
            s = 1.0 / di if di != 0.0 else 0.0
            U[i, 0] = ex * s
            U[i, 1] = ey * s
            U[i, 2] = ez * s
        else:
            U[i, 0] = N[i, 0]
            U[i, 1] = N[i, 1]
            U[i, 2] = N[i, 2]
    return r, U


@numba.njit(cache=True)
def face_residuals(
    X: np.ndarray,
    face: np.ndarray,
    plane: np.ndarray,
    sign: np.ndarray,
    distance: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals and their gradients against one given face per point.

    ``plane[face[i]]`` (F, 12) float64 holds the face's unit normal n and
    ``n . a``, then the dual basis U, V of its edges ab, ac with ``U . a``
    and ``V . a`` (see :func:`inspection._faces.face_planes`). The residual is the signed
    distance of ``x_i`` to the face's plane; with ``distance`` it stands
    for the distance to the triangle, which it equals while the foot point
    lies inside the triangle (barycentric coordinates from U and V). The distance
    to one face is at least the distance to the surface, so a cost evaluated
    this way bounds the true cost from above.

    Also returns, per point, whether another face may now be the closest (the
    caller queries those again and overwrites their residuals): with
    ``distance``, its foot point left the face's interior; in either mode, it
    crossed the face's plane (``sign[i]`` is the sign it had), such as a point
    overhanging a wall that moves back over the part.
    """
    n = X.shape[0]
    r = np.empty(n)
    U = np.empty((n, 3))
    recheck = np.empty(n, dtype=np.bool_)
    for i in range(n):
        f = face[i]
        px, py, pz = X[i, 0], X[i, 1], X[i, 2]
        nx, ny, nz = plane[f, 0], plane[f, 1], plane[f, 2]
        ri = nx * px + ny * py + nz * pz - plane[f, 3]
        r[i] = ri
        U[i, 0] = nx
        U[i, 1] = ny
        U[i, 2] = nz
        again = (ri >= 0.0) != (sign[i] >= 0.0)
        if distance and not again:
            u = plane[f, 4] * px + plane[f, 5] * py + plane[f, 6] * pz - plane[f, 7]
            v = plane[f, 8] * px + plane[f, 9] * py + plane[f, 10] * pz - plane[f, 11]
            again = not (u >= 0.0 and v >= 0.0 and u + v <= 1.0)
        recheck[i] = again
    return r, U, recheck


@numba.njit(cache=True)
def partial_shuffle(n: int, k: int, seed: np.uint64) -> np.ndarray:
    """A permutation of ``range(n)`` whose first ``k`` entries are a uniform
    random sample in random order (Fisher-Yates stopped after ``k`` swaps),
    from a splitmix64 stream seeded with ``seed``: O(k), not O(n)."""
    out = np.arange(n)
    state = np.uint64(seed)
    for i in range(min(k, n - 1)):
        state += np.uint64(0x9E3779B97F4A7C15)
        z = state
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
        j = i + np.int64(z % np.uint64(n - i))
        out[i], out[j] = out[j], out[i]
    return out


@numba.njit(cache=True)
def lm_step(H: np.ndarray, g: np.ndarray, lam: float) -> tuple[np.ndarray, float, bool]:
    """The damped step ``(H + lam D) delta = -g`` and its predicted reduction
    ``-(g . delta + delta . H delta / 2)``. ``D`` is Marquardt's scaling
    ``diag(H)`` plus a small isotropic term, so that directions the data do
    not constrain (``diag(H) ~ 0``) get no step at all."""
    n = H.shape[0]
    tr = 0.0
    for i in range(n):
        tr += H[i, i]
    eps = 1e-9 * max(tr, 1e-300)
    A = H.copy()
    for i in range(n):
        A[i, i] += lam * (H[i, i] + eps)
    delta, ok = cholesky_solve(A, -g)
    if not ok:
        return delta, 0.0, False
    pred = 0.0
    for i in range(n):
        hd = 0.0
        for k in range(n):
            hd += H[i, k] * delta[k]
        pred -= g[i] * delta[i] + 0.5 * delta[i] * hd
    return delta, pred, True


@numba.njit(cache=True)
def trace_inverse(H: np.ndarray) -> float:
    """``trace(H^-1)`` of a symmetric positive definite ``H``; 0 when it is not."""
    n = H.shape[0]
    tr = 0.0
    for j in range(n):
        e = np.zeros(n)
        e[j] = 1.0
        x, ok = cholesky_solve(H, e)
        if not ok:
            return 0.0
        tr += x[j]
    return tr


@numba.njit(cache=True)
def compose(T: np.ndarray, omega: np.ndarray, t: np.ndarray, center: np.ndarray) -> np.ndarray:
    """``x' = R(omega) (x - center) + center + t`` applied after ``T``, with
    ``R(omega)`` the rotation of the rotation vector ``omega`` (Rodrigues)."""
    theta = np.sqrt(omega[0] * omega[0] + omega[1] * omega[1] + omega[2] * omega[2])
    R = np.eye(3)
    if theta < 1e-12:
        # First order: exact to ~theta^2 / 2, below 1e-24.
        R[0, 1] = -omega[2]
        R[0, 2] = omega[1]
        R[1, 0] = omega[2]
        R[1, 2] = -omega[0]
        R[2, 0] = -omega[1]
        R[2, 1] = omega[0]
    else:
        kx, ky, kz = omega[0] / theta, omega[1] / theta, omega[2] / theta
        s = np.sin(theta)
        c1 = 1.0 - np.cos(theta)
        R[0, 0] = 1.0 - c1 * (ky * ky + kz * kz)
        R[1, 1] = 1.0 - c1 * (kx * kx + kz * kz)
        R[2, 2] = 1.0 - c1 * (kx * kx + ky * ky)
        R[0, 1] = c1 * kx * ky - s * kz
        R[1, 0] = c1 * kx * ky + s * kz
        R[0, 2] = c1 * kx * kz + s * ky
        R[2, 0] = c1 * kx * kz - s * ky
        R[1, 2] = c1 * ky * kz - s * kx
        R[2, 1] = c1 * ky * kz + s * kx
    out = np.eye(4)
    for i in range(3):
        for j in range(3):
            out[i, j] = R[i, 0] * T[0, j] + R[i, 1] * T[1, j] + R[i, 2] * T[2, j]
        out[i, 3] = (
            R[i, 0] * (T[0, 3] - center[0])
            + R[i, 1] * (T[1, 3] - center[1])
            + R[i, 2] * (T[2, 3] - center[2])
            + center[i]
            + t[i]
        )
    return out


@numba.njit(cache=True)
def robust_cost(r: np.ndarray, v: np.ndarray, sigma: float, loss: int, c: float) -> float:
    """The cost ``E = sum v sigma^2 rho(r / sigma) / sum v`` over the points with ``v > 0``."""
    s = 0.0
    vs = 0.0
    for i in range(r.shape[0]):
        if v[i] > 0.0:
            rho, _ = rho_weight(r[i], sigma, loss, c)
            s += v[i] * rho
            vs += v[i]
    return s / vs


@numba.njit(cache=True)
def weighted_centroid(X: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid of the points with positive weight, and their RMS radius about it."""
    c = np.zeros(3)
    cnt = 0
    for i in range(X.shape[0]):
        if v[i] > 0.0:
            c[0] += X[i, 0]
            c[1] += X[i, 1]
            c[2] += X[i, 2]
            cnt += 1
    c /= max(cnt, 1)
    s = 0.0
    for i in range(X.shape[0]):
        if v[i] > 0.0:
            dx = X[i, 0] - c[0]
            dy = X[i, 1] - c[1]
            dz = X[i, 2] - c[2]
            s += dx * dx + dy * dy + dz * dz
    return c, np.sqrt(s / max(cnt, 1))


@numba.njit(cache=True)
def cost_normal_equations(
    X: np.ndarray,
    N: np.ndarray,
    r: np.ndarray,
    v: np.ndarray,
    sigma: float,
    loss: int,
    c: float,
    center: np.ndarray,
    L: float,
) -> tuple[float, np.ndarray, np.ndarray]:
    """The robust cost and the IRLS normal equations, in one pass over the points.

    Row i of the Jacobian is ``J_i = [((x_i - center) x n_i) / L, n_i]`` for
    the twist ``(omega L, t)``; ``H = sum w J^T J``, ``g = sum w r J``.
    Returns the cost (as :func:`robust_cost`), H (6, 6) and g (6,), normalised by
    the sum of the input weights.
    """
    # 21 + 6 scalar accumulators: numba keeps them in registers.
    h00 = h01 = h02 = h03 = h04 = h05 = 0.0
    h11 = h12 = h13 = h14 = h15 = 0.0
    h22 = h23 = h24 = h25 = 0.0
    h33 = h34 = h35 = 0.0
    h44 = h45 = 0.0
    h55 = 0.0
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    inv_l = 1.0 / L
    vs = 0.0
    es = 0.0
    for i in range(X.shape[0]):
        vi = v[i]
        if vi <= 0.0:
            continue
        vs += vi
        rho, w = rho_weight(r[i], sigma, loss, c)
        es += vi * rho
        w *= vi
        if w <= 0.0:
            continue
        px = X[i, 0] - center[0]
        py = X[i, 1] - center[1]
        pz = X[i, 2] - center[2]
        nx, ny, nz = N[i, 0], N[i, 1], N[i, 2]
        j0 = (py * nz - pz * ny) * inv_l
        j1 = (pz * nx - px * nz) * inv_l
        j2 = (px * ny - py * nx) * inv_l
        wj0, wj1, wj2, wj3, wj4, wj5 = w * j0, w * j1, w * j2, w * nx, w * ny, w * nz
        h00 += wj0 * j0
        h01 += wj0 * j1
        h02 += wj0 * j2
        h03 += wj0 * nx
        h04 += wj0 * ny
        h05 += wj0 * nz
        h11 += wj1 * j1
        h12 += wj1 * j2
        h13 += wj1 * nx
        h14 += wj1 * ny
        h15 += wj1 * nz
        h22 += wj2 * j2
        h23 += wj2 * nx
        h24 += wj2 * ny
        h25 += wj2 * nz
        h33 += wj3 * nx
        h34 += wj3 * ny
        h35 += wj3 * nz
        h44 += wj4 * ny
        h45 += wj4 * nz
        h55 += wj5 * nz
        ri = r[i]
        g0 += wj0 * ri
        g1 += wj1 * ri
        g2 += wj2 * ri
        g3 += wj3 * ri
        g4 += wj4 * ri
        g5 += wj5 * ri
    H = np.array(
        [
            [h00, h01, h02, h03, h04, h05],
            [h01, h11, h12, h13, h14, h15],
            [h02, h12, h22, h23, h24, h25],
            [h03, h13, h23, h33, h34, h35],
            [h04, h14, h24, h34, h44, h45],
            [h05, h15, h25, h35, h45, h55],
        ]
    )
    g = np.array([g0, g1, g2, g3, g4, g5])
    if vs > 0.0:
        H /= vs
        g /= vs
        es /= vs
    return es, H, g


@numba.njit(cache=True)
def irls_weights(r: np.ndarray, v: np.ndarray, sigma: float, loss: int, c: float) -> np.ndarray:
    """The IRLS weights ``v psi(x) / x``, ``x = r / sigma`` (0 where ``v = 0``)."""
    out = np.zeros(r.shape[0])
    for i in range(r.shape[0]):
        if v[i] > 0.0:
            _, w = rho_weight(r[i], sigma, loss, c)
            out[i] = v[i] * w
    return out


@numba.njit(cache=True)
def median_abs(r: np.ndarray, v: np.ndarray, k: int) -> float:
    """Median of ``|r[i]|`` over the first ``k`` points with ``v[i] > 0`` (0 if none)."""
    a = np.empty(k)
    n = 0
    for i in range(k):
        if v[i] > 0.0:
            a[n] = abs(r[i])
            n += 1
    if n == 0:
        return 0.0
    return np.median(a[:n])


@numba.njit(cache=True)
def turned_away(
    r: np.ndarray, normals: np.ndarray, w: np.ndarray, cos: float, far: float
) -> np.ndarray:
    """``r`` with ``far`` where the normal's cosine to ``w`` is below ``cos`` (a copy
    only if there is such a point; ``r`` itself otherwise)."""
    n = r.shape[0]
    first = n
    for i in range(n):
        if normals[i, 0] * w[0] + normals[i, 1] * w[1] + normals[i, 2] * w[2] < cos:
            first = i
            break
    if first == n:
        return r
    out = r.copy()
    for i in range(first, n):
        if normals[i, 0] * w[0] + normals[i, 1] * w[1] + normals[i, 2] * w[2] < cos:
            out[i] = far
    return out


@numba.njit(cache=True)
def opposed_fraction(normals: np.ndarray, w: np.ndarray) -> float:
    """The weight share of the normals more than 120 degrees from their weighted mean
    (0 when the weights or the mean vanish)."""
    total = 0.0
    mx = my = mz = 0.0
    for i in range(normals.shape[0]):
        total += w[i]
        mx += w[i] * normals[i, 0]
        my += w[i] * normals[i, 1]
        mz += w[i] * normals[i, 2]
    norm = np.sqrt(mx * mx + my * my + mz * mz)
    if total <= 0.0 or norm <= 1e-12 * total:
        return 0.0
    mx, my, mz = mx / norm, my / norm, mz / norm
    opposed = 0.0
    for i in range(normals.shape[0]):
        if normals[i, 0] * mx + normals[i, 1] * my + normals[i, 2] * mz < -0.5:
            opposed += w[i]
    return opposed / total

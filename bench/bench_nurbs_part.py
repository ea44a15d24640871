"""A NURBS part: the pose fitted to the tessellation's tree or to the exact faces.

A crowned 300 x 200 mm rational bicubic panel (its radius ~0.4 m), read
from our STEP writer's file as a part's CAD is (``read_step_nurbs``) and
tessellated on cells of 20, 5 and 2 mm (``tessellate_faces``); 30,000 points
sampled on the exact surface, displaced along its normal by a known smooth
field (+-0.03 mm, the truth) and by 0.01 mm noise, moved to a known pose.
Each cloud is fitted from a start 0.5 mm and 0.1 deg off (``register``, the
line's final fit) once with the tessellation's grid tree and its face planes
(what the measuring sequence does for a mesh) and once with the tree refined
on the exact faces (``ExactTree``, no face planes: every step's residuals on
the design); the deviations are then measured to the exact faces from each
pose. Printed: the pose's error (translation mm, rotation deg), the
deviations' error against the truth (max, RMS and bias, um), and the fit's
wall and CPU time (median of 3).

The tessellation's chords lie inside the convex side: a fit to them moves
the cloud towards them by their mean gap, a bias that every deviation
measured to the exact faces from that pose inherits. The figures say how
large it is for each sampling, and what the exact fit costs.

Run: ``python -m bench nurbs_part`` (``make bench BENCH=nurbs_part``).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import dataclasses  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

POINTS = 30_000
CELLS_MM = (20.0, 5.0, 2.0)
ROUNDS = 3


def panel():  # type: ignore[no-untyped-def]
    """The crowned panel, 300 x 200 mm, crown 30 mm, weights up to 1.3."""
    from inspection.nurbs import Surface

    nu, nv = 6, 5
    gx, gy = np.meshgrid(np.linspace(-150, 150, nu), np.linspace(-100, 100, nv), indexing="ij")
    crown = 30.0 * (1 - (gx / 150) ** 2) * (1 - 0.5 * (gy / 100) ** 2)
    w = np.ones((nu, nv))
    w[2:4, 1:4] = 1.3

    def knots(n: int) -> np.ndarray:
        return np.r_[np.zeros(4), np.linspace(0, 1, n - 2)[1:-1], np.ones(4)]

    return Surface(3, 3, knots(nu), knots(nv), np.stack([gx, gy, crown], -1), w)


def truth_field(uv: np.ndarray) -> np.ndarray:
    """The known deviation (mm) at parameters uv, +-0.03 mm."""
    return 0.03 * np.sin(3 * np.pi * uv[:, 0]) * np.cos(2 * np.pi * uv[:, 1])


def _pose(angle_deg: float, axis: np.ndarray, t: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(
        np.radians(angle_deg) * axis / np.linalg.norm(axis)
    ).as_matrix()
    T[:3, 3] = t
    return T


def main() -> int:
    from inspection import deviations, register
    from inspection.grid import GridTree
    from inspection.measure import MeasureParams
    from inspection.nurbs import ExactTree, read_step_nurbs, tessellate_faces, write_step_surfaces
    from inspection.registration import CadFaces
    from inspection.transforms import apply

    s = panel()
    with tempfile.TemporaryDirectory() as tmp:
        faces = read_step_nurbs(write_step_surfaces(Path(tmp) / "panel.step", [s]))
    rng = np.random.default_rng(7)
    uv = rng.uniform(0.0, 1.0, (POINTS, 2))
    on, su, sv = s.evaluate(uv[:, 0], uv[:, 1], 1)
    n = np.cross(su, sv)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    truth = truth_field(uv)
    pts_cad = on + truth[:, None] * n + rng.normal(0.0, 0.01, on.shape)
    T_data_cad = _pose(7.0, np.array([0.2, 0.3, 1.0]), np.array([40.0, -25.0, 5.0]))
    pts = apply(T_data_cad, pts_cad)
    T_true = np.linalg.inv(T_data_cad)  # T_cad_data
    start = _pose(0.1, np.array([1.0, -0.5, 0.2]), np.array([0.3, -0.3, 0.3])) @ T_true
    rp = MeasureParams().fit_params("rig")
    rp = dataclasses.replace(rp, escape_deg=None)
    print(
        f"panel 300 x 200 mm, crown 30 mm, rational bicubic {s.shape[0]} x {s.shape[1]}; "
        f"{POINTS} points, field +-0.03 mm, noise 0.01 mm; fit from 0.5 mm / 0.1 deg off"
    )
    print(f"{'cells':>6s} {'fit to':>16s} {'triangles':>9s} {'dt um':>7s} {'drot udeg':>9s} "
          f"{'err max um':>10s} {'err rms um':>10s} {'bias um':>8s} {'wall ms':>8s} "
          f"{'CPU ms':>7s} {'iters':>5s}")  # fmt: skip
    for cell in CELLS_MM:
        model = tessellate_faces(faces, cell_mm=cell)
        tree = GridTree.build(model.cad)
        exact = ExactTree(tree, model)
        planes = CadFaces.of(tree)
        for label, query, kw in (("tessellation", tree, {"faces": planes}),
                                 ("exact faces", exact, {})):  # fmt: skip
            runs = []
            for _ in range(ROUNDS):
                w0, c0 = time.perf_counter(), time.process_time()
                fit = register(query, pts, rp, init=start, **kw)
                runs.append((time.perf_counter() - w0, time.process_time() - c0, fit))
            fit = runs[0][2]
            dT = fit.transform @ T_data_cad
            rot = np.degrees(np.arccos(np.clip((np.trace(dT[:3, :3]) - 1) / 2, -1.0, 1.0)))
            dev = deviations(exact, apply(fit.transform, pts))
            err = dev.distances - truth
            print(
                f"{cell:6.0f} {label:>16s} {len(model.cad.faces):9d} "
                f"{np.linalg.norm(dT[:3, 3]) * 1e3:7.2f} {rot * 1e6:9.1f} "
                f"{np.abs(err).max() * 1e3:10.2f} {np.sqrt(np.mean(err**2)) * 1e3:10.2f} "
                f"{err.mean() * 1e3:8.2f} {statistics.median(r[0] for r in runs) * 1e3:8.0f} "
                f"{statistics.median(r[1] for r in runs) * 1e3:7.0f} {fit.iterations:5d}"
            )
    print("(err: the deviation measured to the exact faces from the fitted pose, minus the "
          "truth; the noise of 0.01 mm is in it)")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

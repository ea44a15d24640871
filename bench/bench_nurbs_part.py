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
large it is for each sampling, and what the exact fit costs (its CPU time
against the tessellation fit's, the peer, in the same run).

Part 2, the measuring sequence. Frames of the panel rendered from a 1 mm
sampling at 640 x 512 px, measured by ``measure_frames`` with the part built
on 2 mm cells (the service's default sampling) as a NURBS part and as a mesh
part (the same tree): the deviations stage's wall time, the whole call's
CPU time (medians of 3), and how far the mesh part's deviations lie from
the NURBS part's (the chords' gap).

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
          f"{'CPU ms':>7s} {'CPU x':>6s} {'iters':>5s}")  # fmt: skip
    for cell in CELLS_MM:
        model = tessellate_faces(faces, cell_mm=cell)
        tree = GridTree.build(model.cad)
        exact = ExactTree(tree, model)
        planes = CadFaces.of(tree)
        peer_cpu = None
        for label, query, kw in (("tessellation", tree, {"faces": planes}),
                                 ("exact faces", exact, {})):  # fmt: skip
            runs = []
            for _ in range(ROUNDS):
                w0, c0 = time.perf_counter(), time.process_time()
                fit = register(query, pts, rp, init=start, **kw)
                runs.append((time.perf_counter() - w0, time.process_time() - c0, fit))
            fit = runs[0][2]
            cpu = statistics.median(r[1] for r in runs)
            peer_cpu = cpu if peer_cpu is None else peer_cpu
            dT = fit.transform @ T_data_cad
            rot = np.degrees(np.arccos(np.clip((np.trace(dT[:3, :3]) - 1) / 2, -1.0, 1.0)))
            dev = deviations(exact, apply(fit.transform, pts))
            err = dev.distances - truth
            print(
                f"{cell:6.0f} {label:>16s} {len(model.cad.faces):9d} "
                f"{np.linalg.norm(dT[:3, 3]) * 1e3:7.2f} {rot * 1e6:9.1f} "
                f"{np.abs(err).max() * 1e3:10.2f} {np.sqrt(np.mean(err**2)) * 1e3:10.2f} "
                f"{err.mean() * 1e3:8.2f} {statistics.median(r[0] for r in runs) * 1e3:8.0f} "
                f"{cpu * 1e3:7.0f} {cpu / peer_cpu:6.1f} {fit.iterations:5d}"
            )
    print("(err: the deviation measured to the exact faces from the fitted pose, minus the "
          "truth; the noise of 0.01 mm is in it)")  # fmt: skip
    sequence(faces)
    return 0


def sequence(faces) -> None:  # type: ignore[no-untyped-def]
    """Part 2: the measuring sequence on rendered frames, NURBS part against mesh part."""
    from inspection.measure import PartModel, measure_frames
    from inspection.nurbs import tessellate_faces
    from inspection.reconstruct import Reconstructor
    from inspection.rig import Rig, belt_pose
    from inspection.simulate import simulate

    size = (640, 512)
    nurbs = PartModel.build(tessellate_faces(faces, cell_mm=2.0))
    mesh = dataclasses.replace(nurbs, nurbs=None)
    fine = tessellate_faces(faces, cell_mm=1.0)
    frames = simulate(Rig.nominal(*size), fine.cad, belt_pose(20.0, -10.0, 15.0), seed=3)
    print(f"\nmeasure_frames, {size[0]} x {size[1]} px, tree on 2 mm cells "
          f"({len(nurbs.cad.faces)} triangles)")  # fmt: skip
    print(f"{'part':>6s} {'points':>7s} {'deviations wall ms':>18s} {'total CPU ms':>12s}")
    out = {}
    with Reconstructor.build(Rig.default().with_image_size(*size)) as rec:
        measure_frames(nurbs, rec, frames)  # warm-up
        for label, part in (("mesh", mesh), ("nurbs", nurbs)):
            runs = []
            for _ in range(ROUNDS):
                c0 = time.process_time()
                m = measure_frames(part, rec, frames)
                runs.append((m.timings_ms["deviations"], time.process_time() - c0))
            out[label] = m.deviations.distances  # type: ignore[union-attr]
            print(f"{label:>6s} {len(m.points):7d} {statistics.median(r[0] for r in runs):18.1f} "
                  f"{statistics.median(r[1] for r in runs) * 1e3:12.0f}")  # fmt: skip
    gap = out["mesh"] - out["nurbs"]
    print(
        f"mesh part's deviations minus the NURBS part's (the chords' gap): median "
        f"{np.median(gap) * 1e3:.2f} um, 99th percentile {np.percentile(gap, 99) * 1e3:.2f} um"
    )


if __name__ == "__main__":
    raise SystemExit(main())

"""The Simulator: one rig's precomputed set-up, rendering frame sets and boards.

The set-up (every pixel's ray, the projector slide, the belt texture and the
empty belt's render) is built once per rig and reused for every frame, so it
is an explicit object built with :meth:`Simulator.build`; the cameras render
in parallel threads.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import Any, TypeVar

import cv2
import numba
import numpy as np
import numpy.typing as npt

from .. import _raster
from ..arrays import Image, Transform, mesh_arrays
from ..board import CharucoSpec
from ..errors import InvalidInput
from ..rig import Camera, Rig
from ..transforms import apply
from .exposure import _sub_exposure_shifts, _SubExposure
from .options import _BOARD_PX_PER_MM, _FLOOR_ALBEDO, _TEXEL_MM, CameraTruth, RenderOptions
from .scene import (
    _belt_texture,
    _board_texture,
    _CameraSetup,
    _face_neighbours,
    _kvec,
    _lens_dust,
    _part_dirt,
    _rasterize_view,
)

log = logging.getLogger(__name__)

_T = TypeVar("_T")
_R = TypeVar("_R")


class Simulator:
    """The per-rig state of the renderer; build with :meth:`build`.

    Attributes
    ----------
    rig : Rig
        The rig rendered (the truth).
    """

    def __init__(
        self,
        rig: Rig,
        cams: list[_CameraSetup],
        pattern: npt.NDArray[np.float32],
        belt: npt.NDArray[np.float32],
    ) -> None:
        self.rig = rig
        self._cams = cams
        self._pattern = pattern
        self._belt = belt

    @classmethod
    def build(cls, rig: Rig) -> Simulator:
        """Precompute every pixel's ray, the projector slide and the belt texture."""
        if not isinstance(rig, Rig):
            raise InvalidInput(f"rig must be a Rig, got {type(rig).__name__}")
        p = rig.projector
        pattern = p.pattern.image(p.width, p.height)
        belt = _belt_texture(rig)

        def setup(cam: Camera) -> _CameraSetup:
            xy = cam.undistort(cam.pixel_grid())
            rays = xy.reshape(cam.height, cam.width, 2)
            kv = _kvec(cam.K)
            u = kv[0] * xy[:, 0] + kv[1] * xy[:, 1] + kv[2]
            v = kv[3] * xy[:, 1] + kv[4]
            ox = int(np.floor(u.min())) - 2
            oy = int(np.floor(v.min())) - 2
            shape = (int(np.ceil(v.max())) - oy + 3, int(np.ceil(u.max())) - ox + 3)
            r2 = (xy * xy).sum(axis=1).reshape(cam.height, cam.width)
            vignette = (1.0 / (1.0 + r2) ** 2).astype(np.float32)
            rays = np.ascontiguousarray(rays)
            belt_irr = np.empty((cam.height, cam.width), np.float32)
            belt_q = np.empty((cam.height, cam.width, 4), np.float32)
            belt_alb = np.empty((cam.height, cam.width), np.float32)
            _raster.belt_static(
                rays,
                np.ascontiguousarray(cam.R.T),
                cam.centre,
                p.R,
                p.t,
                _kvec(p.K),
                pattern,
                p.centre,
                p.power,
                float(np.linalg.norm(p.centre)),
                belt,
                _TEXEL_MM,
                rig.conveyor.width_mm / 2.0,
                _FLOOR_ALBEDO,
                RenderOptions.pixel_samples,
                belt_irr,
                belt_q,
                belt_alb,
            )
            # Where a 5 x 5 grid of pixels meets the belt: what the belt's smear is measured on.
            rows = np.linspace(0, cam.height - 1, 5).astype(int)
            cols = np.linspace(0, cam.width - 1, 5).astype(int)
            grid = rays[np.ix_(rows, cols)].reshape(-1, 2)
            d = np.column_stack([grid, np.ones(len(grid))]) @ cam.R
            down = d[:, 2] < 0
            probes = cam.centre - (cam.centre[2] / d[down, 2])[:, None] * d[down]
            extent = float(np.abs(rays).max())
            return _CameraSetup(
                cam, rays, vignette, kv, ox, oy, shape, belt_irr, belt_q, belt_alb, probes, extent
            )

        cams = _per_camera(setup, list(rig.cameras))
        log.debug("simulator built for rig %s", rig.id)
        return cls(rig, cams, pattern, belt)

    # ------------------------------------------------------------------ parts
    def render(
        self,
        mesh: Any,
        T_rig_part: npt.ArrayLike,
        *,
        seed: int = 0,
        options: RenderOptions | None = None,
        return_truth: bool = False,
    ) -> list[Image] | tuple[list[Image], list[CameraTruth]]:
        """Render one flash frame set; see :func:`simulate`."""
        opts = options if options is not None else RenderOptions()
        if not isinstance(opts, RenderOptions):
            raise InvalidInput("options must be a RenderOptions")
        vertices, faces = mesh_arrays(mesh)
        T = _check_transform(T_rig_part, "T_rig_part")
        seed = _check_seed(seed)
        streams = np.random.SeedSequence(seed).spawn(1 + len(self._cams))

        V = apply(T, vertices)
        e1 = V[faces[:, 1]] - V[faces[:, 0]]
        e2 = V[faces[:, 2]] - V[faces[:, 0]]
        n = np.cross(e1, e2)
        norm = np.linalg.norm(n, axis=1)
        good = norm > 1e-12
        if not good.all():
            faces = faces[good]
            n = n[good]
            norm = norm[good]
        normals = np.ascontiguousarray(n / norm[:, None])
        neighbours = _face_neighbours(faces)
        dirt_c, dirt_r, dirt_k = _part_dirt(V, faces, norm, opts.part_dirt_spots, streams[0])
        travel_mm = self.rig.conveyor.speed_mm_s * opts.flash_us * 1e-6
        shifts = _sub_exposure_shifts(V, travel_mm, self._cams)

        rig = self.rig
        p = rig.projector

        def instant(shift_mm: float) -> _SubExposure:
            if shift_mm == 0.0:
                V_k, dirt_k_c = V, dirt_c
            else:
                V_k = V + np.array([shift_mm, 0.0, 0.0])
                dirt_k_c = dirt_c + np.array([shift_mm, 0.0, 0.0])
            d_rig = np.einsum("ij,ij->i", normals, V_k[faces[:, 0]])
            smap_z, smap_f, _, _ = _rasterize_view(
                V_k, faces, p.R, p.t, _kvec(p.K), 0, 0, (p.height, p.width)
            )
            return _SubExposure(shift_mm, V_k, d_rig, smap_z, smap_f, dirt_k_c)

        instants = _per_camera(instant, shifts)
        P = p.centre
        r0 = float(np.linalg.norm(P))

        def shade(
            setup: _CameraSetup,
            at: _SubExposure,
            out: npt.NDArray[np.float32],
            points: npt.NDArray[np.float32],
            flags: npt.NDArray[np.uint8],
            with_truth: bool,
        ) -> None:
            """Render one camera's signal (DN) at one instant of the flash into ``out``."""
            cam = setup.camera
            zb, fb, sx, sy = _rasterize_view(
                at.V, faces, cam.R, cam.t, setup.kvec, setup.ox, setup.oy, setup.buf_shape
            )
            n_c = normals @ cam.R.T
            planes = np.empty((len(faces), 4))
            planes[:, :3] = n_c
            planes[:, 3] = at.d_rig + n_c @ cam.t
            _raster.shade_scene(
                setup.rays,
                setup.kvec,
                setup.ox,
                setup.oy,
                fb,
                zb,
                sx,
                sy,
                faces,
                neighbours,
                planes,
                normals,
                np.ascontiguousarray(cam.R.T),
                cam.centre,
                p.R,
                p.t,
                _kvec(p.K),
                self._pattern,
                at.smap_z,
                at.smap_f,
                P,
                p.power,
                r0,
                opts.ambient,
                opts.part_albedo,
                opts.specular_sharp,
                opts.shininess_sharp,
                opts.specular_broad,
                opts.shininess_broad,
                at.dirt_c,
                dirt_r,
                dirt_k,
                self._belt,
                _TEXEL_MM,
                opts.belt_shift_mm + at.shift_mm,
                rig.conveyor.width_mm / 2.0,
                _FLOOR_ALBEDO,
                setup.belt_irr,
                setup.belt_q,
                setup.belt_alb,
                setup.vignette * np.float32(opts.exposure_dn),
                opts.pixel_samples,
                opts.edge_samples,
                out,
                points,
                flags,
                with_truth,
            )

        def one(
            job: tuple[_CameraSetup, np.random.SeedSequence],
        ) -> tuple[Image, CameraTruth | None]:
            setup, stream = job
            cam = setup.camera
            shape = (cam.height, cam.width)
            out = np.empty(shape, np.float32)
            if return_truth:
                points = np.empty((*shape, 3), np.float32)
                flags = np.empty(shape, np.uint8)
            else:
                points = np.empty((1, 1, 3), np.float32)
                flags = np.empty((1, 1), np.uint8)
            # The truth is what the camera sees at the middle of the flash (shift 0).
            middle = len(instants) // 2
            shade(setup, instants[middle], out, points, flags, return_truth)
            if len(instants) > 1:
                # The sensor integrates over the flash: average the instants' signals.
                part = np.empty(shape, np.float32)
                no_points, no_flags = np.empty((1, 1, 3), np.float32), np.empty((1, 1), np.uint8)
                for k, at in enumerate(instants):
                    if k != middle:
                        shade(setup, at, part, no_points, no_flags, False)
                        out += part
                out *= np.float32(1.0 / len(instants))
            image = self._expose(out, opts, stream)
            if not return_truth:
                return image, None
            truth = CameraTruth(
                points, (flags & 1).astype(bool), (flags & 2).astype(bool), image == 255
            )
            return image, truth

        results = _per_camera(one, list(zip(self._cams, streams[1:], strict=True)))
        images = [image for image, _ in results]
        truths = [truth for _, truth in results if truth is not None]
        return (images, truths) if return_truth else images

    # ----------------------------------------------------------------- boards
    def render_board(
        self,
        T_rig_board: npt.ArrayLike,
        board: CharucoSpec | None = None,
        *,
        seed: int = 0,
        options: RenderOptions | None = None,
        supersample: int = 5,
    ) -> list[Image]:
        """Render a ChArUco board in any pose; see :func:`simulate_board`."""
        spec = board if board is not None else CharucoSpec()
        if not isinstance(spec, CharucoSpec):
            raise InvalidInput("board must be a CharucoSpec")
        opts = options if options is not None else RenderOptions()
        T = _check_transform(T_rig_board, "T_rig_board")
        seed = _check_seed(seed)
        if not 1 <= int(supersample) <= 8:
            raise InvalidInput("supersample must be in [1, 8]")
        tex = _board_texture(spec)
        w, h = spec.size_mm
        lo = np.array([-spec.rim_mm, -spec.rim_mm])
        hi = np.array([w + spec.rim_mm, h + spec.rim_mm])
        streams = np.random.SeedSequence(seed).spawn(len(self._cams))

        def one(job: tuple[_CameraSetup, np.random.SeedSequence]) -> Image:
            setup, stream = job
            cam = setup.camera
            T_cam_board = cam.T_cam_rig @ T
            R_cb = T_cam_board[:3, :3]
            t_cb = T_cam_board[:3, 3]
            n = R_cb[:, 2]  # board z axis in the camera frame
            plane = np.array([n[0], n[1], n[2], n @ t_cb])
            out = np.empty((cam.height, cam.width), np.float32)
            _raster.shade_board(
                setup.rays,
                np.ascontiguousarray(R_cb.T),
                -R_cb.T @ t_cb,
                plane,
                tex,
                _BOARD_PX_PER_MM,
                np.zeros(2),
                lo,
                hi,
                np.ascontiguousarray(cam.R.T),
                cam.centre,
                self._belt,
                _TEXEL_MM,
                opts.belt_shift_mm,
                self.rig.conveyor.width_mm / 2.0,
                _FLOOR_ALBEDO,
                1.0,
                int(supersample),
                setup.vignette * np.float32(opts.board_white_dn / 0.85),
                out,
            )
            # Calibration lighting is diffuse and even (the flash's slide would
            # cover the board with speckle): exposure set by the paper's white.
            return self._expose(out, replace(opts, lens_dirt_spots=0), stream)

        images = _per_camera(one, list(zip(self._cams, streams, strict=True)))
        return images

    # ----------------------------------------------------------------- sensor
    def _expose(
        self, signal: npt.NDArray[np.float32], opts: RenderOptions, stream: np.random.SeedSequence
    ) -> Image:
        """Sensor signal (DN, vignetting applied) -> 8-bit image: lens dust, blur, noise."""
        rng = np.random.default_rng(stream)
        if opts.lens_dirt_spots:
            _lens_dust(signal, opts.lens_dirt_spots, rng)
        if opts.blur_px > 0:
            signal = np.asarray(
                cv2.GaussianBlur(signal, (0, 0), opts.blur_px, borderType=cv2.BORDER_REPLICATE),
                dtype=np.float32,
            )
        key = np.uint64(rng.integers(0, 2**63, dtype=np.int64))
        image = np.empty(signal.shape, np.uint8)
        _raster.sensor_noise(
            signal, key, float(opts.shot_noise), float(opts.read_noise_dn) ** 2, image
        )
        return image


def _per_camera(fn: Callable[[_T], _R], jobs: list[_T]) -> list[_R]:
    """Run ``fn`` over the cameras' jobs in parallel threads, results in order.

    The numba kernels release the GIL, as do OpenCV and numpy's large
    operations, so the threads run truly in parallel; numba's own threading
    layer is not involved (see :mod:`inspection._raster`). Uses as many
    threads as numba is allowed (``NUMBA_NUM_THREADS``). Every camera has its
    own seed stream, so the result does not depend on the thread count.
    """
    workers = min(len(jobs), max(1, numba.get_num_threads()))
    if workers <= 1:
        return [fn(job) for job in jobs]
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="simulate") as pool:
        return list(pool.map(fn, jobs))


# --------------------------------------------------------------------- helpers
def _check_seed(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidInput(f"seed must be a non-negative int, got {seed!r}")
    return int(seed)


def _check_transform(T: Any, what: str) -> Transform:
    try:
        arr = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{what} must be a (4, 4) float array") from exc
    if arr.shape != (4, 4):
        raise InvalidInput(f"{what} must have shape (4, 4), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInput(f"{what} must be finite")
    R = arr[:3, :3]
    if (
        not np.allclose(R @ R.T, np.eye(3), atol=1e-6)
        or np.linalg.det(R) <= 0
        or not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0])
    ):
        raise InvalidInput(
            f"{what} must be a rigid transform (rotation, translation, last row 0 0 0 1)"
        )
    return arr

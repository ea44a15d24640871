"""The rig simulator: four flash frames of a part on the belt, and calibration boards.

What a frame set contains, and why (each is a way real frames are hard):

- The **projected speckle** (the rig's only texture on bare sheet metal), cut
  off by **projector shadows** behind walls and flanges (a shadow map rendered
  from the projector, filtered over four texels so shadow edges are soft).
- **Flash shading**: Lambert with inverse-square fall-off from the projector,
  plus two Blinn-Phong lobes: a broad sheen (each camera sees the metal with a
  different brightness) and a sharp mirror lobe, the flash's own reflection,
  which **saturates** in blobs that carry no pattern.
- **Dirt on the part** (matte dark spots that move with the part) and **on the
  lens** (soft dark out-of-focus blobs fixed in the image).
- A **textured belt** (periodic along x, so it can move) and a dark floor
  beyond it, lit by the same flash.
- **Lens distortion** exactly as OpenCV models it (every pixel's ray is
  undistorted once per rig), vignetting (cos^4), optical blur, and **sensor
  noise** (shot noise with variance proportional to the signal, read noise,
  8-bit quantisation).
- **Pixel area**: a pixel collects the light over its whole area, so the
  projected speckle is averaged over each pixel's footprint on the part (3 x 3
  samples placed through the footprint's Jacobian; ``pixel_samples``). Taken
  at the pixel's centre alone, the speckle's fine grain aliases, and
  differently in each camera: on clean frames of the demo panel that biased
  the mean over a 10 mm disc of the reconstructed top by 0.010 mm RMS, an
  error no real sensor makes (0.006 mm with the area; the simulator's cost
  rose from 0.12 to 0.15 s per frame set).

Rendering: a numba z-buffer per camera into an undistorted buffer, then exact
ray-plane intersections per real pixel (see :mod:`inspection._raster`); the
cameras render in parallel threads (as many as ``NUMBA_NUM_THREADS`` allows). The
per-rig set-up (rays, pattern, belt texture; ~0.5 s) is done once by
:meth:`Simulator.build`; :func:`simulate` keeps the last two simulators, keyed
by the rig's content id.

Everything is deterministic for a seed.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any, Literal, TypeVar, overload

import cv2
import numba
import numpy as np
import numpy.typing as npt

from . import _raster
from .arrays import Image, Transform, mesh_arrays
from .board import CharucoSpec
from .errors import InvalidInput
from .rig import Camera, Rig

log = logging.getLogger(__name__)

_TEXEL_MM = 0.5  # belt texture resolution
_BELT_PERIOD_MM = 1024.0  # the belt texture repeats every metre or so
_BOARD_PX_PER_MM = 8.0
_FLOOR_ALBEDO = 0.04  # the machine floor beyond the belt's edges

_T = TypeVar("_T")
_R = TypeVar("_R")


@dataclass(frozen=True)
class RenderOptions:
    """Photometric and fault parameters of the simulator.

    Attributes
    ----------
    exposure_dn : float
        Grey value (DN) of a white Lambertian surface facing the flash at the
        reference distance (1300 mm) under the bright speckle.
    ambient : float
        Stray light relative to the flash (what lights the projector's shadows).
    part_albedo : float
        Diffuse reflectance of the part (bare steel ~0.45).
    specular_sharp, shininess_sharp : float
        Mirror lobe of the part: strength relative to the flash, Blinn-Phong
        exponent. The default saturates in blobs of a few centimetres.
    specular_broad, shininess_broad : float
        Broad sheen lobe.
    blur_px : float
        Optical blur (Gaussian sigma, pixels).
    pixel_samples : int
        The sensor integrates light over each pixel's area: the projected
        pattern is averaged over the pixel's footprint on the part with
        ``pixel_samples`` x ``pixel_samples`` samples (1: the pixel's centre
        only, which aliases the speckle; see the module notes). The empty
        belt, precomputed per rig, always uses the default.
    shot_noise : float
        Variance of the shot noise per DN of signal.
    read_noise_dn : float
        Standard deviation of the read noise, DN.
    part_dirt_spots : int
        Dirt spots on the part's surface (radius 1.5-5 mm).
    lens_dirt_spots : int
        Dust blobs per lens.
    belt_shift_mm : float
        How far the belt has moved (its texture moves with it).
    board_white_dn : float
        Grey value of the white board paper in calibration images.
    """

    exposure_dn: float = 430.0
    ambient: float = 0.03
    part_albedo: float = 0.45
    specular_sharp: float = 8.0
    shininess_sharp: float = 5000.0
    specular_broad: float = 0.12
    shininess_broad: float = 40.0
    blur_px: float = 0.6
    pixel_samples: int = 3
    shot_noise: float = 0.3
    read_noise_dn: float = 1.2
    part_dirt_spots: int = 6
    lens_dirt_spots: int = 1
    belt_shift_mm: float = 0.0
    board_white_dn: float = 200.0

    def __post_init__(self) -> None:
        for name in (
            "exposure_dn",
            "ambient",
            "part_albedo",
            "specular_sharp",
            "shininess_sharp",
            "specular_broad",
            "shininess_broad",
            "blur_px",
            "shot_noise",
            "read_noise_dn",
            "board_white_dn",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise InvalidInput(f"RenderOptions.{name} must be finite and >= 0, got {value!r}")
        if not 0 < self.part_albedo <= 1:
            raise InvalidInput("RenderOptions.part_albedo must be in (0, 1]")
        if isinstance(self.pixel_samples, bool) or not isinstance(
            self.pixel_samples, (int, np.integer)
        ):
            raise InvalidInput("RenderOptions.pixel_samples must be an int")
        if not 1 <= self.pixel_samples <= 8:
            raise InvalidInput(
                f"RenderOptions.pixel_samples must be in 1..8, got {self.pixel_samples}"
            )
        if self.part_dirt_spots < 0 or self.lens_dirt_spots < 0:
            raise InvalidInput("dirt spot counts must be >= 0")
        if not np.isfinite(self.belt_shift_mm):
            raise InvalidInput("belt_shift_mm must be finite")

    @classmethod
    def clean(cls) -> RenderOptions:
        """No faults: no mirror lobe, no dirt, no noise (for tests of geometry)."""
        return cls(
            specular_sharp=0.0,
            specular_broad=0.0,
            shot_noise=0.0,
            read_noise_dn=0.0,
            part_dirt_spots=0,
            lens_dirt_spots=0,
        )


@dataclass(frozen=True, eq=False)
class CameraTruth:
    """What one camera really saw (ground truth for tests and benchmarks).

    Attributes
    ----------
    points : (H, W, 3) float32, mm, rig frame
        The surface point on each pixel's ray (the part, or the belt at z = 0).
    part : (H, W) bool
        The pixel sees the part.
    lit : (H, W) bool
        The point receives the projected pattern (not in the projector's shadow).
    saturated : (H, W) bool
        The pixel is at 255.
    """

    points: npt.NDArray[np.float32]
    part: npt.NDArray[np.bool_]
    lit: npt.NDArray[np.bool_]
    saturated: npt.NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class _CameraSetup:
    camera: Camera
    rays: npt.NDArray[np.float64]  # (H, W, 2) ideal normalised coordinates
    vignette: npt.NDArray[np.float32]  # (H, W) cos^4
    kvec: npt.NDArray[np.float64]  # fx, skew, cx, fy, cy
    ox: int
    oy: int
    buf_shape: tuple[int, int]
    belt_irr: npt.NDArray[np.float32]  # (H, W) patterned irradiance x cosine on the empty belt
    belt_q: npt.NDArray[np.float32]  # (H, W, 4) slide u, v, projector depth, shadow bias
    belt_alb: npt.NDArray[np.float32]  # (H, W) belt albedo at rest


def _kvec(K: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return np.array([K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]])


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
            return _CameraSetup(cam, rays, vignette, kv, ox, oy, shape, belt_irr, belt_q, belt_alb)

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

        V = vertices @ T[:3, :3].T + T[:3, 3]
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
        d_rig = np.einsum("ij,ij->i", normals, V[faces[:, 0]])

        rig = self.rig
        p = rig.projector
        smap_z, smap_f, _, _ = _rasterize_view(
            V, faces, p.R, p.t, _kvec(p.K), 0, 0, (p.height, p.width)
        )
        dirt_c, dirt_r, dirt_k = _part_dirt(V, faces, norm, opts.part_dirt_spots, streams[0])
        P = p.centre
        r0 = float(np.linalg.norm(P))

        def one(
            job: tuple[_CameraSetup, np.random.SeedSequence],
        ) -> tuple[Image, CameraTruth | None]:
            setup, stream = job
            cam = setup.camera
            zb, fb, sx, sy = _rasterize_view(
                V, faces, cam.R, cam.t, setup.kvec, setup.ox, setup.oy, setup.buf_shape
            )
            n_c = normals @ cam.R.T
            planes = np.empty((len(faces), 4))
            planes[:, :3] = n_c
            planes[:, 3] = d_rig + n_c @ cam.t
            out = np.empty((cam.height, cam.width), np.float32)
            if return_truth:
                points = np.empty((cam.height, cam.width, 3), np.float32)
                flags = np.empty((cam.height, cam.width), np.uint8)
            else:
                points = np.empty((1, 1, 3), np.float32)
                flags = np.empty((1, 1), np.uint8)
            _raster.shade_scene(
                setup.rays,
                setup.kvec,
                setup.ox,
                setup.oy,
                fb,
                sx,
                sy,
                faces,
                planes,
                normals,
                np.ascontiguousarray(cam.R.T),
                cam.centre,
                p.R,
                p.t,
                _kvec(p.K),
                self._pattern,
                smap_z,
                smap_f,
                P,
                p.power,
                r0,
                opts.ambient,
                opts.part_albedo,
                opts.specular_sharp,
                opts.shininess_sharp,
                opts.specular_broad,
                opts.shininess_broad,
                dirt_c,
                dirt_r,
                dirt_k,
                self._belt,
                _TEXEL_MM,
                opts.belt_shift_mm,
                rig.conveyor.width_mm / 2.0,
                _FLOOR_ALBEDO,
                setup.belt_irr,
                setup.belt_q,
                setup.belt_alb,
                setup.vignette * np.float32(opts.exposure_dn),
                opts.pixel_samples,
                out,
                points,
                flags,
                return_truth,
            )
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


# ---------------------------------------------------------------------- public
_CACHE: dict[str, Simulator] = {}
_CACHE_LOCK = threading.Lock()
_CACHE_SIZE = 2


def simulator_for(rig: Rig) -> Simulator:
    """The :class:`Simulator` of a rig, built once and kept (the last two rigs, by content id)."""
    if not isinstance(rig, Rig):
        raise InvalidInput(f"rig must be a Rig, got {type(rig).__name__}")
    key = rig.id
    with _CACHE_LOCK:
        sim = _CACHE.get(key)
    if sim is None:
        sim = Simulator.build(rig)
        with _CACHE_LOCK:
            _CACHE[key] = sim
            while len(_CACHE) > _CACHE_SIZE:
                _CACHE.pop(next(iter(_CACHE)))
    return sim


@overload
def simulate(
    rig: Rig,
    mesh: Any,
    T_rig_part: npt.ArrayLike,
    *,
    seed: int = ...,
    options: RenderOptions | None = ...,
    return_truth: Literal[False] = ...,
) -> list[Image]: ...
@overload
def simulate(
    rig: Rig,
    mesh: Any,
    T_rig_part: npt.ArrayLike,
    *,
    seed: int = ...,
    options: RenderOptions | None = ...,
    return_truth: Literal[True],
) -> tuple[list[Image], list[CameraTruth]]: ...
def simulate(
    rig: Rig,
    mesh: Any,
    T_rig_part: npt.ArrayLike,
    *,
    seed: int = 0,
    options: RenderOptions | None = None,
    return_truth: bool = False,
) -> list[Image] | tuple[list[Image], list[CameraTruth]]:
    """Render the four flash frames of a part lying on the belt.

    Parameters
    ----------
    rig : Rig
        The rig to render with: the truth (normally :meth:`Rig.nominal`).
    mesh : trimesh.Trimesh, CadModel, or anything with ``vertices`` (V, 3)
        and ``faces`` (F, 3)
        The part in its own frame, mm.
    T_rig_part : (4, 4) float64
        Pose of the part: maps part-frame points into the rig frame.
    seed : int
        Seeds the faults (dirt) and the sensor noise; the same seed gives the
        same images, bit for bit.
    options : RenderOptions, optional
        Photometry and faults (default: :class:`RenderOptions` ()).
    return_truth : bool
        Also return what each camera really saw.

    Returns
    -------
    images : list of four (H, W) uint8
        In the order of ``rig.cameras``.
    truths : list of four CameraTruth
        Only with ``return_truth=True``.

    Raises
    ------
    InvalidInput
        For a mesh without faces or with non-finite vertices, a transform that
        is not a finite rigid 4 x 4 matrix, or a bad seed.
    """
    return simulator_for(rig).render(
        mesh, T_rig_part, seed=seed, options=options, return_truth=return_truth
    )


def simulate_board(
    rig: Rig,
    T_rig_board: npt.ArrayLike,
    board: CharucoSpec | None = None,
    *,
    seed: int = 0,
    options: RenderOptions | None = None,
    supersample: int = 5,
) -> list[Image]:
    """Render a printed ChArUco board in any pose, under even calibration lighting.

    Parameters
    ----------
    rig : Rig
        The rig (the truth).
    T_rig_board : (4, 4) float64
        Maps board-frame points (see :mod:`inspection.board`) into the rig frame.
    board : CharucoSpec, optional
        Board layout (default :class:`CharucoSpec` ()).
    seed : int
        Seeds the sensor noise.
    options : RenderOptions, optional
        Sensor parameters (noise, blur, belt shift).
    supersample : int
        Rays per pixel along each axis: area sampling, as a sensor's pixels
        integrate light. With 3 the board's edges alias: its corners were
        found 0.12 px RMS off on the board lying on the belt (0.09 px with 5),
        and the calibrated rig frame came out tilted by up to 0.012 deg.

    Returns
    -------
    list of four (H, W) uint8
    """
    return simulator_for(rig).render_board(
        T_rig_board, board, seed=seed, options=options, supersample=supersample
    )


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


def _rasterize_view(V, faces, R, t, kvec, ox, oy, shape):
    """Depth and face buffers of a mesh seen by a pinhole (R, t, K) in a buffer at (ox, oy),
    and the projected vertices (buffer pixels)."""
    q = V @ R.T + t
    z = q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = q[:, 0] / z
        yn = q[:, 1] / z
    sx = kvec[0] * xn + kvec[1] * yn + kvec[2] - ox
    sy = kvec[3] * yn + kvec[4] - oy
    sx = np.where(z > _raster.NEAR_MM, sx, 0.0)
    sy = np.where(z > _raster.NEAR_MM, sy, 0.0)
    zbuf = np.full(shape, np.inf, np.float32)
    fbuf = np.full(shape, -1, np.int32)
    _raster.rasterize(sx, sy, z, faces, zbuf, fbuf)
    return zbuf, fbuf, sx, sy


def _part_dirt(V, faces, double_area, count, stream):
    """Dirt spots on the part surface: centres, radii and remaining reflectance."""
    if count == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    rng = np.random.default_rng(stream)
    prob = double_area / double_area.sum()
    idx = rng.choice(len(faces), size=count, p=prob)
    r1 = np.sqrt(rng.random(count))
    r2 = rng.random(count)
    a = V[faces[idx, 0]]
    b = V[faces[idx, 1]]
    c = V[faces[idx, 2]]
    centres = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    radii = rng.uniform(1.5, 5.0, count)
    keep = rng.uniform(0.15, 0.5, count)
    return np.ascontiguousarray(centres), radii, keep


def _lens_dust(img: npt.NDArray[np.float32], count: int, rng: np.random.Generator) -> None:
    """Darken ``img`` in place with soft out-of-focus dust blobs."""
    H, W = img.shape
    for _ in range(count):
        cx = rng.uniform(0, W)
        cy = rng.uniform(0, H)
        r = rng.uniform(20.0, 60.0)
        depth = rng.uniform(0.25, 0.55)
        x0, x1 = max(int(cx - r), 0), min(int(cx + r) + 1, W)
        y0, y1 = max(int(cy - r), 0), min(int(cy + r) + 1, H)
        if x0 >= x1 or y0 >= y1:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        s = np.clip(1.0 - np.hypot(xx - cx, yy - cy) / r, 0.0, 1.0)
        img[y0:y1, x0:x1] *= (1.0 - depth * s * s * (3.0 - 2.0 * s)).astype(np.float32)


def _belt_texture(rig: Rig) -> npt.NDArray[np.float32]:
    """Belt albedo: fine fabric grain plus coarse wear, periodic along x."""
    conv = rig.conveyor
    tx = int(round(_BELT_PERIOD_MM / _TEXEL_MM))
    ty = int(np.ceil(conv.width_mm / _TEXEL_MM)) + 2
    rng = np.random.default_rng(conv.texture_seed)
    pad = 96
    noise = rng.standard_normal((ty + 2 * pad, tx), dtype=np.float32)
    wrapped = np.concatenate([noise[:, -pad:], noise, noise[:, :pad]], axis=1)

    def smooth(sigma: float) -> npt.NDArray[np.float32]:
        out = cv2.GaussianBlur(wrapped, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        out = out[pad:-pad, pad:-pad]
        return out / out.std()

    fine = smooth(1.2)  # ~0.6 mm fabric grain
    coarse = smooth(20.0)  # ~10 mm mottling and wear
    t = 0.8 * fine + 0.6 * coarse
    t /= t.std()
    albedo = conv.albedo * np.clip(1.0 + conv.texture_contrast * t, 0.2, 2.0)
    return np.ascontiguousarray(albedo.astype(np.float32))


_BOARD_TEXTURES: dict[CharucoSpec, npt.NDArray[np.uint8]] = {}


def _board_texture(spec: CharucoSpec) -> npt.NDArray[np.uint8]:
    tex = _BOARD_TEXTURES.get(spec)
    if tex is None:
        tex = np.ascontiguousarray(spec.texture(_BOARD_PX_PER_MM))
        _BOARD_TEXTURES.clear()  # one board at a time is the normal case
        _BOARD_TEXTURES[spec] = tex
    return tex

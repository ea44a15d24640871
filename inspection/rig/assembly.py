"""The rig: four cameras, the pattern projector and the conveyor, as built or as calibrated.

:meth:`Rig.nominal` is the rig as built (the simulator's truth);
:meth:`Rig.default` the calibrated rig the line measures with.
"""

from __future__ import annotations

import hashlib
import importlib.resources
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidInput
from .camera import Camera
from .conveyor import Conveyor
from .poses import look_at, rotvec_matrix
from .projector import Projector
from .toml import RIG_FORMAT, parse_toml, rig_from_dict, rig_to_toml, write_rig

ENV_RIG = "INSPECTION_RIG"
"""Environment variable naming a rig TOML file that :meth:`Rig.default` reads instead."""

DEFAULT_RIG_DATA = "data/rig.toml"
"""The calibrated rig shipped with the package: package data of ``inspection``
(``inspection/data/rig.toml``, declared in pyproject.toml), so that an installed
wheel has it. :meth:`Rig.default` reads it."""

# The measurement volume (x, y, z extents, mm) the nominal rig is built for.
VOLUME_MM = (800.0, 500.0, 200.0)


@dataclass(frozen=True, eq=False)
class Rig:
    """Four cameras, the pattern projector and the conveyor, in the rig frame.

    Attributes
    ----------
    cameras : tuple of Camera
        Four cameras (``cam0`` .. ``cam3``, see :mod:`inspection.rig`).
    projector : Projector
    conveyor : Conveyor
    stereo_pairs : tuple of (int, int)
        The pairs a reconstruction should rectify first (left, right): the two
        pairs with baselines along x, left camera at lower x.
    ring_pairs : tuple of (int, int)
        Further pairs with baselines along y (first camera at lower y).
    source : str
        How the numbers were obtained ("nominal", or a calibration summary).
    reprojection_rms_px : tuple of float
        Per camera, the RMS reprojection error of the calibration (empty for
        the nominal rig).
    """

    cameras: tuple[Camera, ...]
    projector: Projector
    conveyor: Conveyor = field(default_factory=Conveyor)
    stereo_pairs: tuple[tuple[int, int], ...] = ((0, 1), (2, 3))
    ring_pairs: tuple[tuple[int, int], ...] = ((0, 2), (1, 3))
    source: str = "nominal"
    reprojection_rms_px: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        if len(cams) != 4 or not all(isinstance(c, Camera) for c in cams):
            raise InvalidInput(f"a rig has four Camera objects, got {len(cams)}")
        names = [c.name for c in cams]
        if len(set(names)) != 4:
            raise InvalidInput(f"camera names must be unique, got {names}")
        object.__setattr__(self, "cameras", cams)
        for attr in ("stereo_pairs", "ring_pairs"):
            pairs = tuple((int(a), int(b)) for a, b in getattr(self, attr))
            for a, b in pairs:
                if not (0 <= a < 4 and 0 <= b < 4 and a != b):
                    raise InvalidInput(f"{attr}: bad camera pair {(a, b)}")
            object.__setattr__(self, attr, pairs)
        rms = tuple(float(r) for r in self.reprojection_rms_px)
        if rms and len(rms) != 4:
            raise InvalidInput("reprojection_rms_px has one value per camera, or none")
        object.__setattr__(self, "reprojection_rms_px", rms)

    # -- access --------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        if isinstance(key, str):
            for cam in self.cameras:
                if cam.name == key:
                    return cam
            raise KeyError(key)
        return self.cameras[key]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)

    @property
    def image_shape(self) -> tuple[int, int]:
        """(height, width) of the first camera's images (all four are equal in the default rigs)."""
        return self.cameras[0].shape

    # -- identity ------------------------------------------------------------
    @property
    def id(self) -> str:
        """Calibration id: the first 16 hex digits of SHA-256 over the content.

        Computed from every number and name that :meth:`save` writes (except
        ``source``), so a saved and reloaded rig keeps its id, and any edit
        changes it. Results record it as ``calibration_id``.
        """
        h = hashlib.sha256()
        h.update(RIG_FORMAT.encode())
        for cam in self.cameras:
            h.update(cam.name.encode() + b"\0")
            h.update(np.array([cam.width, cam.height], dtype=np.int64).tobytes())
            for arr in (cam.K, cam.dist, cam.R, cam.t):
                h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
        p = self.projector
        h.update(np.array([p.width, p.height], dtype=np.int64).tobytes())
        for arr in (p.K, p.R, p.t):
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
        h.update(
            repr((p.pattern, p.power, self.conveyor, self.stereo_pairs, self.ring_pairs)).encode()
        )
        return h.hexdigest()[:16]

    # -- construction --------------------------------------------------------
    @classmethod
    def nominal(cls, width: int = 1280, height: int = 1024) -> Rig:
        """The rig as built: the simulator's truth.

        Four cameras with 8 mm lenses on 1280 x 1024, 4.8 µm sensors, 1300 mm
        above the belt at (±250, ±300) mm, looking at (0, 0, 100); each with
        its own small mounting errors, principal point offset and lens
        distortion, as a real rig has. Other image sizes scale the sensor
        (same field of view).

        Parameters
        ----------
        width, height : int
            Image size in pixels.
        """
        f_px = 8.0 / 0.0048  # 8 mm lens, 4.8 µm pixels
        target = np.array([0.0, 0.0, 100.0])
        # As-built deviations from the drawing: mounting angle errors (rad),
        # position errors (mm), principal point offsets (px) and distortion.
        # Fixed numbers, so the truth never changes with library versions.
        built = [
            # name, (x, y), d_angle (rx, ry, rz), d_pos, d_pp, dist
            (
                "cam0",
                (-250.0, -300.0),
                (0.004, -0.003, 0.006),
                (1.2, -0.8, 2.1),
                (6.2, -4.1),
                (-0.082, 0.071, 0.0006, -0.0004, -0.012),
            ),
            (
                "cam1",
                (250.0, -300.0),
                (-0.002, 0.005, -0.004),
                (-0.7, 1.5, -1.3),
                (-3.5, 5.4),
                (-0.091, 0.088, -0.0003, 0.0005, -0.021),
            ),
            (
                "cam2",
                (-250.0, 300.0),
                (0.003, 0.002, 0.003),
                (0.4, 0.9, -0.6),
                (2.8, 7.3),
                (-0.076, 0.062, 0.0004, 0.0002, -0.008),
            ),
            (
                "cam3",
                (250.0, 300.0),
                (-0.005, -0.004, -0.005),
                (-1.6, -0.3, 1.7),
                (-5.9, -2.2),
                (-0.087, 0.079, -0.0005, -0.0003, -0.016),
            ),
        ]
        cams = []
        for name, (x, y), d_ang, d_pos, d_pp, dist in built:
            C = np.array([x, y, 1300.0]) + np.array(d_pos)
            R = rotvec_matrix(np.array(d_ang)) @ look_at(C, target)
            K = np.array(
                [
                    [f_px * 1.0004, 0.0, 639.5 + d_pp[0]],
                    [0.0, f_px * 0.9997, 511.5 + d_pp[1]],
                    [0.0, 0.0, 1.0],
                ]
            )
            cam = Camera(name, 1280, 1024, K, np.array(dist), R, -R @ C)
            if (width, height) != (1280, 1024):
                cam = cam.with_size(width, height)
            cams.append(cam)
        C_p = np.array([0.0, 0.0, 1300.0])
        R_p = look_at(C_p, np.array([0.0, 0.0, 0.0]))
        K_p = np.array([[2300.0, 0.0, 959.5], [0.0, 2300.0, 599.5], [0.0, 0.0, 1.0]])
        projector = Projector(1920, 1200, K_p, R_p, -R_p @ C_p)
        return cls(tuple(cams), projector, Conveyor(), source="nominal")

    @classmethod
    def default(cls) -> Rig:
        """The calibrated rig the line measures with.

        Reads ``$INSPECTION_RIG`` if set, else the rig shipped with the package
        (:data:`DEFAULT_RIG_DATA`, produced by ``inspection calibrate`` from
        rendered ChArUco images), which an installed wheel carries as package
        data.

        Raises
        ------
        FileNotFoundError
            When ``$INSPECTION_RIG`` names no file, or the package lacks its
            rig (an incomplete installation).
        InvalidInput
            When it is not a valid rig file.
        """
        env = os.environ.get(ENV_RIG)
        if env:
            path = Path(env)
            if not path.is_file():
                raise FileNotFoundError(
                    f"no rig calibration at {path} (from ${ENV_RIG}): "
                    f"run `inspection calibrate --out {path}`"
                )
            return cls.load(path)
        resource = importlib.resources.files("inspection").joinpath(DEFAULT_RIG_DATA)
        try:
            text = resource.read_text(encoding="utf-8")
        except FileNotFoundError as exc:
            raise FileNotFoundError(
                f"the package's calibrated rig {resource} is missing: the installation is "
                "incomplete (the wheel must carry it as package data)"
            ) from exc
        return cls.from_toml(text, where=str(resource))

    def with_image_size(self, width: int, height: int) -> Rig:
        """This rig with every camera's image scaled to ``width`` x ``height``."""
        cams = tuple(c.with_size(width, height) for c in self.cameras)
        return Rig(
            cams,
            self.projector,
            self.conveyor,
            self.stereo_pairs,
            self.ring_pairs,
            self.source,
            self.reprojection_rms_px,
        )

    # -- TOML ----------------------------------------------------------------
    def to_toml(self) -> str:
        """The rig as documented TOML text (see :meth:`save`)."""
        return rig_to_toml(self)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the rig as TOML (floats written exactly, so a reload is bit-identical).

        Returns
        -------
        Path
            The path written.
        """
        return write_rig(self, path)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Rig:
        """Read a rig TOML file written by :meth:`save` (or by hand, same layout).

        Raises
        ------
        FileNotFoundError
            When the file does not exist.
        InvalidInput
            When the file is not valid TOML, misses keys, has unknown keys, or
            its ``id`` does not match its content.
        """
        p = Path(path)
        return cls.from_toml(p.read_text(encoding="utf-8"), where=str(p))

    @classmethod
    def from_toml(cls, text: str, *, where: str = "rig") -> Rig:
        """Read a rig from TOML text written by :meth:`to_toml`.

        ``where`` names the text's origin in error messages.

        Raises
        ------
        InvalidInput
            As :meth:`load`.
        """
        return cls.from_dict(parse_toml(text, where), where=where)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, where: str = "rig") -> Rig:
        """Build a rig from the parsed TOML structure (see :meth:`to_toml`)."""
        return rig_from_dict(cls, data, where)

    def summary(self) -> str:
        """A few lines for people: cameras, centres, pairs."""
        out = [f"rig {self.id} ({self.source})"]
        for cam in self.cameras:
            out.append(
                f"  {cam.name}: {cam.width}x{cam.height} "
                f"f=({cam.K[0, 0]:.1f}, {cam.K[1, 1]:.1f}) px "
                f"centre={np.round(cam.centre, 1).tolist()} mm"
            )
        out.append(f"  stereo pairs {self.stereo_pairs}, ring pairs {self.ring_pairs}")
        return "\n".join(out)

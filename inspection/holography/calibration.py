"""Calibration of the holographic head from one hologram of a reference plate.

1. **The lobes** are found in the plate hologram's spectrum
   (:func:`~inspection.holography.spectrum.find_lobes`), and each cut is then
   centred where its reconstruction's speckles do not move on refocusing
   (:func:`~inspection.holography.lobecut.minimise_cut`).
2. **Each lobe's reference wave** (tilt and quadratic phase): the lobe's
   field ``O W*`` carries the wave's phase, whose local gradient is the local
   spatial frequency; propagated from ``-dz`` to ``+dz``, a speckle pattern
   moves by ``2 dz`` times its direction of travel (Fourier shift theorem on
   the angular spectrum), here ``D(x) = -2 dz (tilt + C x)`` with ``C`` the
   phase's symmetric curvature matrix ``[[c_xx, c_xy], [c_xy, c_yy]]`` (a
   sphere: ``c_xx = c_yy = 1 / radius``, ``c_xy = 0``; the rest is
   astigmatism). The displacements of the reconstructions' intensities,
   window by window (:func:`~inspection.holography.correlation.correlate`),
   are fitted by least squares for (tilt_x, tilt_y, c_xx, c_xy, c_yy), or,
   with ``CalibrateParams.astigmatism`` off, for the sphere alone. The flat
   plate's own phase has no gradient, so it moves nothing.
3. **The phase difference's residual**: tilts good to a few microradians still
   leave a ramp of radians in the two lasers' phase difference over the
   field, far beyond what a shape measurement may keep. The plate's known
   height predicts that difference, ``4 pi z / synthetic``; the rest
   (tilt, curvature and offset of the difference) is fitted by maximising the
   coherent sum ``|sum O1 O2* exp(-i (4 pi z / L + m(x)))|``, started from the
   FFT peak over a few curvatures. It also fixes the absolute phase: heights
   are measured from the head frame's z = 0.

The calibration is stored as TOML with an id (SHA-256 of its content) that
results carry, as the rig's calibration is.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize

from ..errors import CalibrationError, InvalidInput
from .correlation import Displacement, correlate
from .head import ASTIGMATISM_HALF_MM, HoloHead, ReferenceWave
from .lobecut import minimise_cut
from .propagate import propagate
from .spectrum import Field, Lobe, find_lobes, lobe_field, spectrum

log = logging.getLogger(__name__)

HOLO_FORMAT = "inspection-holography/1"


@dataclass(frozen=True)
class LobeCalibration:
    """One laser's lobe and its reference wave as measured.

    ``displacement_rms_px`` is the RMS of the speckle displacements about the
    fitted model; ``windows`` how many windows it was fitted on.
    """

    lobe: Lobe
    wave: ReferenceWave
    displacement_rms_px: float
    windows: int


@dataclass(frozen=True)
class PhaseResidual:
    """The phase difference's residual model
    ``m(x) = a x + b y + c (x^2 + y^2) / 2 + e (x^2 - y^2) / 2 + f x y + d``:
    ``a``, ``b`` in rad/mm, ``c``, ``e``, ``f`` in rad/mm^2, ``d`` in rad;
    ``coherence`` is the normalised coherent sum it reached on the plate (1:
    every pixel agreed). ``e`` and ``f`` (the difference's astigmatism) are 0
    when the calibration models spheres only."""

    a: float
    b: float
    c: float
    d: float
    coherence: float
    e: float = 0.0
    f: float = 0.0

    def phase(self, x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> npt.NDArray:
        return (
            self.a * x
            + self.b * y
            + 0.5 * self.c * (x * x + y * y)
            + 0.5 * self.e * (x * x - y * y)
            + self.f * x * y
            + self.d
        )


@dataclass(frozen=True)
class HoloCalibration:
    """The calibrated head: design, both lobes with their waves, the residual."""

    head: HoloHead
    lobes: tuple[LobeCalibration, LobeCalibration]
    residual: PhaseResidual
    source: str = ""

    @property
    def id(self) -> str:
        """The first 16 hex digits of SHA-256 over every number it holds (not ``source``)."""
        return hashlib.sha256(repr(_numbers(self)).encode()).hexdigest()[:16]

    def object_fields(self, image: npt.ArrayLike) -> tuple[Field, Field]:
        """Both lasers' object fields ``O1``, ``O2`` of a hologram: each lobe cut and
        multiplied by its measured reference wave, (n, n) complex128."""
        spec = spectrum(image)
        if spec.shape != (self.head.pixels,) * 2:
            raise InvalidInput(
                f"the calibration is for {self.head.pixels} x {self.head.pixels} px images, "
                f"got {spec.shape}"
            )
        x, y = self.head.grid()
        out = []
        for lc, wavelength in zip(self.lobes, self.head.wavelengths_mm, strict=True):
            out.append(lobe_field(spec, lc.lobe) * np.exp(1j * lc.wave.phase(x, y, wavelength)))
        return out[0], out[1]

    def difference(self, image: npt.ArrayLike) -> Field:
        """``O1 O2*`` corrected by the residual: its phase is ``4 pi z / synthetic``
        (mod 2 pi) for a surface at height z, (n, n) complex128."""
        o1, o2 = self.object_fields(image)
        x, y = self.head.grid()
        return o1 * np.conj(o2) * np.exp(-1j * self.residual.phase(x, y))

    # -- TOML ----------------------------------------------------------------
    def to_toml(self) -> str:
        h = self.head
        lines = [
            "# Calibration of the dual-wavelength holographic head (see",
            "# inspection.holography.calibration). Units: mm, mrad, rad; lobes in FFT bins",
            "# (row, column; signed). id: SHA-256 of the content, checked on load.",
            "",
            f'format = "{HOLO_FORMAT}"',
            f'id = "{self.id}"',
            f"source = {_quote(self.source)}",
            "",
            "[head]",
            f"pixels = {h.pixels}",
            f"field_mm = {h.field_mm!r}",
            f"wavelength_mm = {h.wavelength_mm!r}",
            f"synthetic_mm = {h.synthetic_mm!r}",
            f"na = {h.na!r}",
            "design = ["
            + ", ".join(
                f"[{r.tilt_x_mrad!r}, {r.tilt_y_mrad!r}, {_num(r.radius_mm)}]" for r in h.references
            )
            + "]",
        ]
        for lc in self.lobes:
            w, lb = lc.wave, lc.lobe
            lines += [
                "",
                "[[lobe]]",
                f"row = {lb.row!r}",
                f"col = {lb.col!r}",
                f"radius = {lb.radius!r}",
                f"tilt_x_mrad = {w.tilt_x_mrad!r}",
                f"tilt_y_mrad = {w.tilt_y_mrad!r}",
                f"radius_mm = {_num(w.radius_mm)}",
                f"astigmatism_rad = {w.astigmatism_rad!r}",
                f"astigmatism45_rad = {w.astigmatism45_rad!r}",
                f"displacement_rms_px = {lc.displacement_rms_px!r}",
                f"windows = {lc.windows}",
            ]
        r = self.residual
        lines += [
            "",
            "[residual]",
            f"a = {r.a!r}",
            f"b = {r.b!r}",
            f"c = {r.c!r}",
            f"d = {r.d!r}",
            f"coherence = {r.coherence!r}",
            f"e = {r.e!r}",
            f"f = {r.f!r}",
            "",
        ]
        return "\n".join(lines)

    def save(self, path: str | os.PathLike[str]) -> Path:
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(out.suffix + ".tmp")
        tmp.write_text(self.to_toml(), encoding="utf-8")
        tmp.replace(out)
        return out

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> HoloCalibration:
        p = Path(path)
        return cls.from_toml(p.read_text(encoding="utf-8"), where=str(p))

    @classmethod
    def from_toml(cls, text: str, *, where: str = "calibration") -> HoloCalibration:
        """Read a calibration written by :meth:`to_toml`.

        Raises
        ------
        InvalidInput
            Not TOML, another format, missing or unknown keys, or an ``id`` that does
            not match the content.
        """
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise InvalidInput(f"{where}: not valid TOML: {exc}") from exc
        if data.get("format") != HOLO_FORMAT:
            raise InvalidInput(
                f"{where}: format must be {HOLO_FORMAT!r}, got {data.get('format')!r}"
            )
        try:
            _keys(data, {"format", "id", "source", "head", "lobe", "residual"}, where)
            hd = data["head"]
            _keys(
                hd, {"pixels", "field_mm", "wavelength_mm", "synthetic_mm", "na", "design"}, where
            )
            head = HoloHead(
                pixels=int(hd["pixels"]),
                field_mm=float(hd["field_mm"]),
                wavelength_mm=float(hd["wavelength_mm"]),
                synthetic_mm=float(hd["synthetic_mm"]),
                na=float(hd["na"]),
                references=tuple(
                    ReferenceWave(float(t[0]), float(t[1]), float(t[2])) for t in hd["design"]
                ),  # type: ignore[arg-type]
            )
            lobes = []
            for lb in data["lobe"]:
                _keys(
                    lb,
                    {"row", "col", "radius", "tilt_x_mrad", "tilt_y_mrad", "radius_mm",
                     "astigmatism_rad", "astigmatism45_rad", "displacement_rms_px", "windows"},
                    where,
                )  # fmt: skip
                lobes.append(
                    LobeCalibration(
                        lobe=Lobe(float(lb["row"]), float(lb["col"]), float(lb["radius"])),
                        wave=ReferenceWave(
                            float(lb["tilt_x_mrad"]),
                            float(lb["tilt_y_mrad"]),
                            float(lb["radius_mm"]),
                            # Calibrations from before the astigmatism was modelled have none.
                            astigmatism_rad=float(lb.get("astigmatism_rad", 0.0)),
                            astigmatism45_rad=float(lb.get("astigmatism45_rad", 0.0)),
                        ),
                        displacement_rms_px=float(lb["displacement_rms_px"]),
                        windows=int(lb["windows"]),
                    )
                )
            if len(lobes) != 2 or len(head.references) != 2:
                raise InvalidInput(f"{where}: needs exactly two lobes and two design waves")
            rs = data["residual"]
            _keys(rs, {"a", "b", "c", "d", "coherence", "e", "f"}, where)
            calib = cls(
                head=head,
                lobes=(lobes[0], lobes[1]),
                residual=PhaseResidual(
                    a=float(rs["a"]),
                    b=float(rs["b"]),
                    c=float(rs["c"]),
                    d=float(rs["d"]),
                    coherence=float(rs["coherence"]),
                    # Calibrations from before the astigmatism was modelled have none.
                    e=float(rs.get("e", 0.0)),
                    f=float(rs.get("f", 0.0)),
                ),
                source=str(data.get("source", "")),
            )
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            if isinstance(exc, InvalidInput):
                raise
            raise InvalidInput(f"{where}: malformed calibration: {exc!r}") from exc
        if "id" in data and data["id"] != calib.id:
            raise InvalidInput(
                f"{where}: id {data['id']!r} does not match the content ({calib.id!r})"
            )
        return calib


@dataclass(frozen=True)
class CalibrateParams:
    """How to calibrate: the two reconstruction planes (``-dz_mm``, ``+dz_mm``) and the
    correlation windows."""

    dz_mm: float = 30.0
    window: int = 64
    min_peak: float = 0.3
    astigmatism: bool = True
    """Fit each wave's curvature along x, y and the diagonals apart (any quadratic phase);
    off: one curvature for both axes (a spherical wave)."""
    minimise_cut: bool = True
    """Centre each lobe's cut where its speckles do not move on refocusing
    (:func:`~inspection.holography.lobecut.minimise_cut`), starting from the spectrum's
    peak; off: the peak's cut (:func:`~inspection.holography.spectrum.find_lobes`)."""


def calibrate_head(
    head: HoloHead,
    image: npt.ArrayLike,
    *,
    plate_height_mm: float = 0.0,
    params: CalibrateParams | None = None,
) -> HoloCalibration:
    """Calibrate both lobes of ``head`` from one hologram of a flat plate lying at
    ``plate_height_mm`` (head frame), perpendicular to the head's axis.

    Raises
    ------
    InvalidInput
        The image does not fit the head.
    CalibrationError
        Too few speckle windows correlate to fit a wave.
    """
    params = params or CalibrateParams()
    if not math.isfinite(plate_height_mm):
        raise InvalidInput("plate_height_mm must be finite")
    lobes = find_lobes(head, image)
    moved = ""
    if params.minimise_cut:
        cut = minimise_cut(head, image, lobes, window=params.window, min_peak=params.min_peak)
        moved = (
            ", lobe cut moved "
            + " / ".join(
                f"{math.hypot(a.row - b.row, a.col - b.col):.2f}"
                for a, b in zip(cut.lobes, cut.start, strict=True)
            )
            + " bins from the spectrum's peak by its speckle displacements"
        )
        lobes = cut.lobes
    spec = spectrum(image)
    x, y = head.grid()
    cals = []
    for lobe, wavelength in zip(lobes, head.wavelengths_mm, strict=True):
        field = lobe_field(spec, lobe)
        disp = plane_displacements(head, field, wavelength, params.dz_mm, params.window)
        cals.append(_fit_wave(head, lobe, disp, wavelength, params))
    calib = HoloCalibration(
        head=head,
        lobes=(cals[0], cals[1]),
        residual=PhaseResidual(0.0, 0.0, 0.0, 0.0, 0.0),
    )
    gamma = calib.difference(image) * np.exp(
        -1j * 4.0 * np.pi * plate_height_mm / head.synthetic_mm
    )
    residual = _fit_residual(gamma, x, y, astigmatism=params.astigmatism)
    log.debug("holography calibration: residual %s", residual)
    return HoloCalibration(
        head=head,
        lobes=calib.lobes,
        residual=residual,
        source=(
            f"flat plate at z = {plate_height_mm:g} mm, planes +-{params.dz_mm:g} mm, "
            f"phase coherence {residual.coherence:.3f}{moved}"
        ),
    )


def plane_displacements(
    head: HoloHead, field: Field, wavelength_mm: float, dz_mm: float, window: int = 64
) -> Displacement:
    """Speckle displacements (px) of ``field``'s intensity from the plane ``-dz_mm`` to
    ``+dz_mm``."""
    a = propagate(field, -dz_mm, wavelength_mm, head.pitch_mm)
    b = propagate(field, dz_mm, wavelength_mm, head.pitch_mm)
    return correlate(np.abs(a) ** 2, np.abs(b) ** 2, window=window)


def _fit_wave(
    head: HoloHead, lobe: Lobe, disp: Displacement, wavelength_mm: float, params: CalibrateParams
) -> LobeCalibration:
    # D(x) = -2 dz (tilt + C x): linear in (tx, ty, c_xx, c_xy, c_yy), or in
    # (tx, ty, c) for a sphere (C = c I).
    n = head.pixels
    good = disp.good(min_peak=params.min_peak)
    xs = (disp.cols - (n - 1) / 2.0) * head.pitch_mm
    ys = (disp.rows - (n - 1) / 2.0) * head.pitch_mm
    s = -2.0 * params.dz_mm
    unknowns = 5 if params.astigmatism else 3
    for _ in range(2):  # a second fit without the windows beyond 3 sigma
        m = int(good.sum())
        if m < 6:  # two equations each: at least twice as many as the unknowns
            raise CalibrationError(f"only {m} speckle windows correlate: cannot fit the wave")
        A = _design(xs[good], ys[good], unknowns) * s
        rhs = np.concatenate([disp.dx[good], disp.dy[good]]) * head.pitch_mm
        sol, *_ = np.linalg.lstsq(A, rhs, rcond=None)
        res = (rhs - A @ sol) / head.pitch_mm
        rms = float(np.sqrt(np.mean(res**2)))
        model = (_design(xs, ys, unknowns) * s @ sol).reshape(2, -1) / head.pitch_mm
        full = np.hypot(disp.dx - model[0], disp.dy - model[1])
        good = good & (full <= 3.0 * max(rms, 1e-3) * math.sqrt(2.0))
    if params.astigmatism:
        cxx, cxy, cyy = (float(v) for v in sol[2:])
    else:
        cxx, cxy, cyy = float(sol[2]), 0.0, float(sol[2])
    # C = c I + a [[1, 0], [0, -1]] + b [[0, 1], [1, 0]]: sphere and the two astigmatisms.
    c, a = 0.5 * (cxx + cyy), 0.5 * (cxx - cyy)
    k_h2 = 2.0 * math.pi / wavelength_mm * ASTIGMATISM_HALF_MM**2
    wave = ReferenceWave(
        float(sol[0]) * 1e3,
        float(sol[1]) * 1e3,
        math.inf if c == 0 else 1.0 / c,
        astigmatism_rad=0.5 * k_h2 * a,
        astigmatism45_rad=0.5 * k_h2 * cxy,
    )
    return LobeCalibration(lobe=lobe, wave=wave, displacement_rms_px=rms, windows=int(good.sum()))


def _design(
    xs: npt.NDArray[np.float64], ys: npt.NDArray[np.float64], unknowns: int
) -> npt.NDArray[np.float64]:
    """Rows ``[dx; dy]`` of ``D / (-2 dz)`` in (tx, ty, c) or (tx, ty, c_xx, c_xy, c_yy)."""
    m = len(xs)
    A = np.zeros((2 * m, unknowns))
    A[:m, 0] = 1.0
    A[m:, 1] = 1.0
    if unknowns == 3:
        A[:m, 2] = xs
        A[m:, 2] = ys
    else:
        A[:m, 2] = xs
        A[:m, 3] = ys
        A[m:, 3] = xs
        A[m:, 4] = ys
    return A


def _fit_residual(
    gamma: Field,
    x: npt.NDArray[np.float64],
    y: npt.NDArray[np.float64],
    *,
    astigmatism: bool = True,
) -> PhaseResidual:
    n = gamma.shape[0]
    pitch = float(x[0, 1] - x[0, 0])
    r2 = 0.5 * (x * x + y * y)
    total = float(np.abs(gamma).sum())
    if total <= 0:
        raise CalibrationError("the plate hologram holds no interference")
    pad = 2 * n
    f = np.fft.fftfreq(pad, d=pitch) * 2.0 * np.pi  # rad/mm
    half_field = float(x.max())
    best = (-1.0, 0.0, 0.0, 0.0)
    # Curvatures up to a few radians at the field's corner, in steps that keep the
    # coherent sum of the right one near its maximum.
    for c in np.linspace(-8.0, 8.0, 33) / half_field**2:
        spec = np.abs(np.fft.fft2(gamma * np.exp(-1j * c * r2), s=(pad, pad)))
        i, j = np.unravel_index(int(spec.argmax()), spec.shape)
        if spec[i, j] > best[0]:
            best = (float(spec[i, j]), float(f[j]), float(f[i]), float(c))
    # The terms m(x) is made of: tilts, sphere, and (modelled) the two astigmatisms.
    terms = [x, y, r2] + ([0.5 * (x * x - y * y), x * y] if astigmatism else [])

    def cost(p: npt.NDArray[np.float64]) -> tuple[float, npt.NDArray[np.float64]]:
        m = sum(pk * g for pk, g in zip(p, terms, strict=True))
        s = np.sum(gamma * np.exp(-1j * m))
        mag = abs(s)
        # d|S|/dp = Re(conj(S) dS/dp) / |S|, dS/dp = sum(-i g e^{-im} dm/dp).
        t = -1j * gamma * np.exp(-1j * m)
        grad = np.array([(np.conj(s) * np.sum(t * g)).real / mag for g in terms], dtype=np.float64)
        return -mag / total, -grad / total

    start = np.array(list(best[1:]) + [0.0] * (len(terms) - 3))
    res = minimize(cost, start, jac=True, method="BFGS")
    p = [float(v) for v in res.x] + [0.0] * (5 - len(terms))
    m = sum(pk * g for pk, g in zip(p, [x, y, r2, 0.5 * (x * x - y * y), x * y], strict=True))
    s = np.sum(gamma * np.exp(-1j * m))
    return PhaseResidual(
        a=p[0], b=p[1], c=p[2], d=float(np.angle(s)), coherence=float(abs(s)) / total,
        e=p[3], f=p[4],
    )  # fmt: skip


def _numbers(c: HoloCalibration) -> tuple[Any, ...]:
    h = c.head
    return (
        HOLO_FORMAT,
        h.pixels,
        h.field_mm,
        h.wavelength_mm,
        h.synthetic_mm,
        h.na,
        tuple((r.tilt_x_mrad, r.tilt_y_mrad, r.radius_mm) for r in h.references),
        tuple(
            (
                lc.lobe.row,
                lc.lobe.col,
                lc.lobe.radius,
                lc.wave.tilt_x_mrad,
                lc.wave.tilt_y_mrad,
                lc.wave.radius_mm,
                lc.displacement_rms_px,
                lc.windows,
            )
            # A wave without astigmatism hashes as before it was modelled: the ids of
            # earlier calibrations stay valid.
            + (
                (lc.wave.astigmatism_rad, lc.wave.astigmatism45_rad)
                if lc.wave.astigmatism_rad or lc.wave.astigmatism45_rad
                else ()
            )
            for lc in c.lobes
        ),
        (c.residual.a, c.residual.b, c.residual.c, c.residual.d, c.residual.coherence)
        + ((c.residual.e, c.residual.f) if c.residual.e or c.residual.f else ()),
    )


def _num(v: float) -> str:
    return "inf" if math.isinf(v) and v > 0 else "-inf" if math.isinf(v) else repr(v)


def _quote(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _keys(d: dict[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise InvalidInput(f"{where}: unknown keys {unknown}")

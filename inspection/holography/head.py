"""The small-field holographic head: its optics, its reference waves and its noise.

The head looks straight down its own -z axis at an ``field_mm`` square field,
imaged (object side) onto ``pixels`` x ``pixels`` sensor pixels. Two lasers of
nearby wavelengths light the part at once; each interferes with its own
off-axis reference wave on the sensor, so that one image holds two holograms
whose spectra sit in separate places (the lobes). The two lasers do not
interfere with each other (their beat is far beyond any pixel's bandwidth).

Head frame: x along the sensor's columns, y along its rows, z towards the
head; pixel (row i, column j) looks along -z from
``((j - (n - 1) / 2) p, (i - (n - 1) / 2) p)`` with ``p = field_mm / pixels``.
Units: mm; angles in mrad; frequencies in cycles/mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..errors import InvalidInput

SPEED_OF_LIGHT_MM_S = 2.99792458e11

# Where the lobes sit, as fractions of the Nyquist frequency along each axis: on the
# diagonals, as far out as the band allows, so that a lobe (radius r), its twin
# and the central term (the object's autocorrelation, radius 2 r) never meet.
LOBE_POSITION = 0.65
LOBE_BUDGET = 0.3  # largest lobe radius (NA plus the reference curvature's spread) / Nyquist
ASTIGMATISM_HALF_MM = 9.0
"""Half width of the 18 mm field: the astigmatism's phase is stated at that radius."""


@dataclass(frozen=True)
class ReferenceWave:
    """One off-axis reference wave at the sensor (object-side coordinates).

    Its phase is ``k (tilt_x x + tilt_y y + (x^2 + y^2) / (2 radius))``: a
    plane wave tilted by ``tilt_*_mrad``, curved with the radius ``radius_mm``
    (positive: diverging; ``inf``: plane); the astigmatism on top is a phase
    over the 18 mm field's half width (:data:`ASTIGMATISM_HALF_MM`), not scaled
    by the wavenumber. Together: any quadratic phase.
    """

    tilt_x_mrad: float
    tilt_y_mrad: float
    radius_mm: float = math.inf
    astigmatism_rad: float = 0.0
    """Phase of ``(x^2 - y^2) / h^2`` on top (``h`` = :data:`ASTIGMATISM_HALF_MM`): the
    curvatures along x and y differ."""
    astigmatism45_rad: float = 0.0
    """Phase of ``2 x y / h^2`` on top: the same, along the diagonals."""

    @property
    def curvature_per_m(self) -> float:
        """1 / radius, in 1/m (0 for a plane wave)."""
        return 0.0 if math.isinf(self.radius_mm) else 1000.0 / self.radius_mm

    def phase(
        self, x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], wavelength_mm: float
    ) -> npt.NDArray[np.float64]:
        """The wave's phase (rad) at object-side positions ``x``, ``y`` (mm)."""
        k = 2.0 * math.pi / wavelength_mm
        out = k * 1e-3 * (self.tilt_x_mrad * x + self.tilt_y_mrad * y)
        if not math.isinf(self.radius_mm):
            out = out + k * (x * x + y * y) / (2.0 * self.radius_mm)
        if self.astigmatism_rad:
            out = out + self.astigmatism_rad * (x * x - y * y) / ASTIGMATISM_HALF_MM**2
        if self.astigmatism45_rad:
            out = out + self.astigmatism45_rad * 2.0 * x * y / ASTIGMATISM_HALF_MM**2
        return out

    def curvatures(self, wavelength_mm: float) -> tuple[float, float, float]:
        """``(c_xx, c_xy, c_yy)``, 1/mm: the phase's quadratic part is
        ``k (c_xx x^2 + 2 c_xy x y + c_yy y^2) / 2`` at ``wavelength_mm``."""
        k = 2.0 * math.pi / wavelength_mm
        c = 0.0 if math.isinf(self.radius_mm) else 1.0 / self.radius_mm
        a = 2.0 * self.astigmatism_rad / (k * ASTIGMATISM_HALF_MM**2)
        b = 2.0 * self.astigmatism45_rad / (k * ASTIGMATISM_HALF_MM**2)
        return c + a, b, c - a


@dataclass(frozen=True)
class HoloHead:
    """The head as designed: field, pixels, wavelengths, aperture, reference waves.

    ``references`` are the design's waves; a real head's (and the simulator's
    injected ones) differ from them, which calibration measures.
    """

    pixels: int
    field_mm: float
    wavelength_mm: float
    synthetic_mm: float
    na: float
    references: tuple[ReferenceWave, ReferenceWave]

    def __post_init__(self) -> None:
        if self.pixels < 64 or self.pixels % 2:
            raise InvalidInput(f"pixels must be even and >= 64, got {self.pixels}")
        for name in ("field_mm", "wavelength_mm", "synthetic_mm", "na"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InvalidInput(f"{name} must be finite and > 0, got {v}")
        if self.synthetic_mm <= 10 * self.wavelength_mm:
            raise InvalidInput("synthetic_mm must be far longer than the wavelength")
        if self.lobe_radius > LOBE_BUDGET * self.nyquist:
            raise InvalidInput(
                f"na {self.na} is too large for {self.pixels} pixels over {self.field_mm} mm: "
                f"the lobes would overlap (radius {self.lobe_radius:.2f} c/mm, "
                f"at most {LOBE_BUDGET * self.nyquist:.2f})"
            )

    @classmethod
    def small_field(cls, pixels: int = 512, *, field_mm: float = 18.0) -> HoloHead:
        """The 18 x 18 mm head: 633 nm and a second laser giving a 1.1 mm synthetic
        wavelength, the aperture filling 0.22 of the band, plane reference waves
        putting the lobes on the diagonals of the spectrum."""
        wavelength = 633e-6
        nyquist = pixels / (2.0 * field_mm)
        tilt = LOBE_POSITION * nyquist * wavelength * 1e3
        return cls(
            pixels=pixels,
            field_mm=field_mm,
            wavelength_mm=wavelength,
            synthetic_mm=1.1,
            na=0.22 * nyquist * wavelength,
            references=(ReferenceWave(-tilt, -tilt), ReferenceWave(-tilt, tilt)),
        )

    def as_built(self) -> tuple[ReferenceWave, ReferenceWave]:
        """The reference waves of the simulated head as built: the design's tilted by about
        a tenth of a mrad and curved (radii of tens of metres), as a real head's differ from
        its design; what the simulated line records with and its calibration finds."""
        r = self.references
        return (
            ReferenceWave(r[0].tilt_x_mrad + 0.11, r[0].tilt_y_mrad - 0.07, 50_000.0),
            ReferenceWave(r[1].tilt_x_mrad - 0.05, r[1].tilt_y_mrad + 0.09, -70_000.0),
        )

    # -- derived -------------------------------------------------------------
    @property
    def wavelengths_mm(self) -> tuple[float, float]:
        """(lambda1, lambda2), lambda2 chosen so that lambda1 lambda2 / (lambda2 - lambda1)
        is the synthetic wavelength."""
        l1 = self.wavelength_mm
        return l1, l1 * self.synthetic_mm / (self.synthetic_mm - l1)

    @property
    def pitch_mm(self) -> float:
        """Object-side pixel pitch, mm."""
        return self.field_mm / self.pixels

    @property
    def nyquist(self) -> float:
        """Nyquist frequency of the sensor, cycles/mm."""
        return 0.5 / self.pitch_mm

    @property
    def cutoff(self) -> float:
        """The aperture's cut-off frequency NA / lambda, cycles/mm."""
        return self.na / self.wavelength_mm

    @property
    def lobe_radius(self) -> float:
        """Radius of a lobe in the spectrum: the aperture's cut-off widened by the
        reference curvature's spread of local frequencies over the field, cycles/mm."""
        half_diag = self.field_mm / math.sqrt(2.0)
        spread = max(abs(r.curvature_per_m) * 1e-3 for r in self.references) * half_diag
        return self.cutoff + spread / self.wavelength_mm

    @property
    def speckle_mm(self) -> float:
        """Mean speckle diameter at the sensor, object side: 1.22 lambda / NA (Airy)."""
        return 1.22 * self.wavelength_mm / self.na

    @property
    def interval_mm(self) -> float:
        """Height of one phase interval (2 pi of the phase difference): half the
        synthetic wavelength (the light goes there and back)."""
        return self.synthetic_mm / 2.0

    def grid(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Object-side pixel centres: (x, y), each (n, n) float64, mm."""
        c = (np.arange(self.pixels, dtype=np.float64) - (self.pixels - 1) / 2.0) * self.pitch_mm
        x, y = np.meshgrid(c, c)
        return x, y


@dataclass(frozen=True)
class HoloNoise:
    """What makes a simulated hologram a real one: sensor, speckle, lasers.

    Speckle is fully developed: the surface's micro-height has ``roughness_um``
    RMS (far above a quarter wavelength), the same for both lasers, so the two
    speckle patterns agree except where the height changes within a speckle.
    The lasers' finite linewidths (Lorentzian) lower the fringe contrast by
    ``exp(-pi linewidth |path difference| / c)``; ``path_mismatch_mm`` is the
    object arm's length minus the reference arm's at height 0.
    """

    bit_depth: int = 12
    full_well_e: float = 10_000.0
    read_noise_e: float = 6.0
    reference_ratio: float = 4.0
    """Mean reference intensity over mean object intensity, per laser."""
    exposure: float = 0.45
    """Mean recorded intensity as a fraction of full scale (bright speckles may clip)."""
    roughness_um: float = 1.0
    linewidths_mhz: tuple[float, float] = (1.0, 1.0)
    path_mismatch_mm: float = 50.0

    def __post_init__(self) -> None:
        if not 8 <= self.bit_depth <= 16:
            raise InvalidInput(f"bit_depth must be 8..16, got {self.bit_depth}")
        for name in ("full_well_e", "reference_ratio", "exposure"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InvalidInput(f"{name} must be finite and > 0, got {v}")
        if self.read_noise_e < 0 or self.roughness_um < 0:
            raise InvalidInput("read_noise_e and roughness_um must be >= 0")
        if len(self.linewidths_mhz) != 2 or min(self.linewidths_mhz) < 0:
            raise InvalidInput("linewidths_mhz must be two values >= 0")

    def visibility(self, path_mm: npt.NDArray[np.float64], laser: int) -> npt.NDArray[np.float64]:
        """Fringe contrast (0..1) at the path differences ``path_mm`` for one laser."""
        dnu = self.linewidths_mhz[laser] * 1e6
        return np.exp(-math.pi * dnu * np.abs(path_mm) / SPEED_OF_LIGHT_MM_S)


def describe(head: HoloHead, noise: HoloNoise) -> str:
    """One line stating the head and noise model, to print beside every figure."""
    l1, l2 = head.wavelengths_mm
    return (
        f"{head.pixels}x{head.pixels} px over {head.field_mm:g} x {head.field_mm:g} mm "
        f"({head.pitch_mm * 1e3:.1f} um/px), lambda {l1 * 1e6:.3f} / {l2 * 1e6:.3f} nm "
        f"(synthetic {head.synthetic_mm:g} mm, interval {head.interval_mm:g} mm), "
        f"NA {head.na:.5f}, speckle {head.speckle_mm * 1e3:.0f} um "
        f"({head.speckle_mm / head.pitch_mm:.1f} px), {noise.bit_depth} bit, "
        f"full well {noise.full_well_e:.0f} e-, read noise {noise.read_noise_e:g} e-, "
        f"reference/object {noise.reference_ratio:g}, roughness {noise.roughness_um:g} um RMS, "
        f"linewidths {noise.linewidths_mhz[0]:g} / {noise.linewidths_mhz[1]:g} MHz "
        f"at {noise.path_mismatch_mm:g} mm path mismatch"
    )

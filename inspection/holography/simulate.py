"""The hologram simulator: a part's CAD at a pose under the holographic head.

For each laser (wavenumber k), the rough surface at height z(x, y) sends back
the field ``exp(i 2 k (z + s))``, s the micro-height (fully developed speckle);
the head's aperture keeps the spatial frequencies below NA / lambda; on the
sensor the field meets its laser's reference wave, with the fringe contrast
its linewidth leaves at that path difference. The two lasers' intensities add
(they do not interfere with each other); the sensor counts photo-electrons
(shot noise), adds read noise and quantises to its bit depth. Deviations
(dents) move the true surface along the CAD normal; the reference waves
(tilt and curvature) are the head's aberrations to calibrate.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..arrays import Transform
from ..errors import InvalidInput
from .depth import depth_map
from .head import HoloHead, HoloNoise, ReferenceWave

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HoloTruth:
    """What the simulator knows, per pixel (head frame, mm).

    Attributes
    ----------
    height_mm : (n, n) float64
        The true surface's z (the CAD's moved by the deviation); NaN off the part.
    cad_height_mm : (n, n) float64
        The CAD's z at the simulated pose.
    deviation_mm : (n, n) float64
        The injected deviation along the CAD normal.
    normals : (n, n, 3) float64
        The CAD's normals.
    references : the reference waves the hologram was recorded with.
    """

    height_mm: npt.NDArray[np.float64]
    cad_height_mm: npt.NDArray[np.float64]
    deviation_mm: npt.NDArray[np.float64]
    normals: npt.NDArray[np.float64]
    references: tuple[ReferenceWave, ReferenceWave]


def simulate_hologram(
    head: HoloHead,
    mesh: object,
    T_head_part: Transform,
    *,
    deviation_mm: npt.NDArray[np.float64] | None = None,
    references: tuple[ReferenceWave, ReferenceWave] | None = None,
    noise: HoloNoise | None = None,
    seed: int = 0,
) -> tuple[npt.NDArray[np.uint16], HoloTruth]:
    """Record one dual-wavelength hologram.

    Parameters
    ----------
    head : HoloHead
    mesh : a trimesh mesh (or anything with vertices and faces), part frame, mm
    T_head_part : (4, 4) float64
        The part's pose in the head frame.
    deviation_mm : (n, n) float64, optional
        Deviation of the true surface from the CAD along its normal, per pixel.
    references : two ReferenceWave, optional
        The waves actually recorded with (default: the head's design).
    noise : HoloNoise, optional
    seed : int
        Seeds the speckle and the sensor noise.

    Returns
    -------
    image : (n, n) uint16
        Digital numbers, 0 .. 2**bit_depth - 1.
    truth : HoloTruth
    """
    noise = noise or HoloNoise()
    refs = references or head.references
    n = head.pixels
    if deviation_mm is None:
        deviation = np.zeros((n, n))
    else:
        deviation = np.asarray(deviation_mm, dtype=np.float64)
        if deviation.shape != (n, n) or not np.all(np.isfinite(deviation)):
            raise InvalidInput(f"deviation_mm must be a finite ({n}, {n}) array")
    depth = depth_map(head, mesh, T_head_part)
    hit = depth.hit
    if hit.mean() < 0.5:
        raise InvalidInput(f"the part covers only {hit.mean():.0%} of the field")
    nz = np.where(hit, depth.normals[..., 2], 1.0)
    height = np.where(hit, depth.height_mm + deviation / nz, np.nan)

    rng = np.random.default_rng(seed)
    micro = rng.normal(0.0, noise.roughness_um * 1e-3, size=(n, n))
    z = np.where(hit, height, 0.0) + micro
    x, y = head.grid()
    fy = np.fft.fftfreq(n, d=head.pitch_mm)
    f2 = fy[:, None] ** 2 + fy[None, :] ** 2

    intensity = np.zeros((n, n))
    for laser, (wavelength, ref) in enumerate(zip(head.wavelengths_mm, refs, strict=True)):
        k = 2.0 * np.pi / wavelength
        obj = np.where(hit, np.exp(1j * 2.0 * k * z), 0.0)
        pupil = f2 <= (head.na / wavelength) ** 2
        obj = np.fft.ifft2(np.fft.fft2(obj) * pupil)
        o2 = obj.real**2 + obj.imag**2
        ref_intensity = noise.reference_ratio * float(o2.mean())
        wave = np.sqrt(ref_intensity) * np.exp(1j * ref.phase(x, y, wavelength))
        # The object arm is 2 z shorter than at height 0: there and back.
        path = noise.path_mismatch_mm - 2.0 * np.where(hit, height, 0.0)
        contrast = noise.visibility(path, laser)
        intensity += o2 + ref_intensity + 2.0 * contrast * (obj * np.conj(wave)).real

    full = 2**noise.bit_depth - 1
    electrons = intensity * (noise.exposure * noise.full_well_e / float(intensity.mean()))
    electrons = rng.poisson(electrons).astype(np.float64)
    electrons += rng.normal(0.0, noise.read_noise_e, size=electrons.shape)
    dn = np.clip(np.rint(electrons * full / noise.full_well_e), 0, full).astype(np.uint16)
    log.debug("hologram: %.2f%% pixels saturated", 100.0 * float((dn == full).mean()))
    truth = HoloTruth(
        height_mm=height,
        cad_height_mm=depth.height_mm,
        deviation_mm=np.where(hit, deviation, np.nan),
        normals=depth.normals,
        references=refs,
    )
    return dn, truth

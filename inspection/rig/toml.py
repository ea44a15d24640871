"""The rig file: a rig as documented TOML text with its content id, and back.

Floats are written with their shortest exact representation (``repr``), so a
saved and reloaded rig is bit for bit the same and keeps its id.
"""

from __future__ import annotations

import logging
import math
import os
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InvalidInput
from .camera import Camera
from .conveyor import Conveyor
from .projector import Pattern, Projector

if TYPE_CHECKING:
    from .assembly import Rig

log = logging.getLogger(__name__)

RIG_FORMAT = "inspection-rig/1"


def rig_to_toml(rig: Rig) -> str:
    """The rig as documented TOML text (see :meth:`Rig.to_toml`)."""
    f = _fmt
    lines = [
        "# The four-camera flash rig of the inspection line.",
        "#",
        "# Frame: origin at the centre of the measurement volume on the conveyor",
        "# surface; x along the conveyor's motion, y across it, z up. Units: mm.",
        "# Cameras use OpenCV's model: X_cam = R @ X_rig + t, then the pinhole K",
        "# (pixels; pixel centres at integer coordinates) with the distortion",
        "# dist = [k1, k2, p1, p2, k3]. R, t map rig -> camera.",
        "# id: SHA-256 of the content (first 16 hex digits), checked on load; delete",
        "# the line after editing numbers by hand.",
        "",
        f'format = "{RIG_FORMAT}"',
        f'id = "{rig.id}"',
        f"source = {_quote(rig.source)}",
        f"stereo_pairs = {f([list(p) for p in rig.stereo_pairs])}",
        f"ring_pairs = {f([list(p) for p in rig.ring_pairs])}",
    ]
    if rig.reprojection_rms_px:
        lines.append(f"reprojection_rms_px = {f(list(rig.reprojection_rms_px))}")
    for cam in rig.cameras:
        lines += [
            "",
            "[[camera]]",
            f"name = {_quote(cam.name)}",
            f"width = {cam.width}",
            f"height = {cam.height}",
            f"K = {f(cam.K.tolist())}",
            f"dist = {f(cam.dist.tolist())}",
            f"R = {f(cam.R.tolist())}",
            f"t = {f(cam.t.tolist())}",
            f"# centre in the rig frame (mm, read only): {np.round(cam.centre, 3).tolist()}",
        ]
    p = rig.projector
    pat = p.pattern
    c = rig.conveyor
    lines += [
        "",
        "[projector]",
        "# pinhole without distortion; R, t map rig -> projector",
        f"width = {p.width}",
        f"height = {p.height}",
        f"K = {f(p.K.tolist())}",
        f"R = {f(p.R.tolist())}",
        f"t = {f(p.t.tolist())}",
        f"power = {f(p.power)}",
        "",
        "[projector.pattern]",
        f"kind = {_quote(pat.kind)}",
        f"seed = {pat.seed}",
        f"grain_px = {f(pat.grain_px)}",
        f"blur_px = {f(pat.blur_px)}",
        f"low = {f(pat.low)}",
        f"high = {f(pat.high)}",
        "",
        "[conveyor]",
        f"speed_mm_s = {f(c.speed_mm_s)}",
        f"surface_z_mm = {f(c.surface_z_mm)}",
        f"width_mm = {f(c.width_mm)}",
        f"albedo = {f(c.albedo)}",
        f"texture_contrast = {f(c.texture_contrast)}",
        f"texture_seed = {c.texture_seed}",
        "",
    ]
    return "\n".join(lines)


def write_rig(rig: Rig, path: str | os.PathLike[str]) -> Path:
    """Write the rig's TOML to ``path`` through a temporary file; returns the path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text(rig.to_toml(), encoding="utf-8")
    tmp.replace(out)
    log.debug("saved rig %s to %s", rig.id, out)
    return out


def parse_toml(text: str, where: str) -> dict[str, Any]:
    """The TOML text parsed, else InvalidInput naming ``where``."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InvalidInput(f"{where}: not valid TOML: {exc}") from exc
    return data


def rig_from_dict(cls: type[Rig], data: dict[str, Any], where: str) -> Rig:
    """A ``cls`` rig from the parsed TOML structure (see :meth:`Rig.from_dict`)."""
    try:
        _keys(
            data,
            {
                "format",
                "id",
                "source",
                "stereo_pairs",
                "ring_pairs",
                "reprojection_rms_px",
                "camera",
                "projector",
                "conveyor",
            },
            where,
        )
        if data.get("format") != RIG_FORMAT:
            raise InvalidInput(
                f"{where}: format must be {RIG_FORMAT!r}, got {data.get('format')!r}"
            )
        cams = []
        for i, c in enumerate(data["camera"]):
            _keys(c, {"name", "width", "height", "K", "dist", "R", "t"}, f"{where}: camera {i}")
            cams.append(
                Camera(c["name"], c["width"], c["height"], c["K"], c["dist"], c["R"], c["t"])
            )
        pj = dict(data["projector"])
        _keys(pj, {"width", "height", "K", "R", "t", "power", "pattern"}, f"{where}: projector")
        pattern = Pattern(**pj.pop("pattern", {}))
        projector = Projector(pattern=pattern, **pj)
        conveyor = Conveyor(**data.get("conveyor", {}))
        rig = cls(
            tuple(cams),
            projector,
            conveyor,
            stereo_pairs=tuple(tuple(x) for x in data.get("stereo_pairs", ((0, 1), (2, 3)))),
            ring_pairs=tuple(tuple(x) for x in data.get("ring_pairs", ((0, 2), (1, 3)))),
            source=str(data.get("source", "")),
            reprojection_rms_px=tuple(data.get("reprojection_rms_px", ())),
        )
    except KeyError as exc:
        raise InvalidInput(f"{where}: missing key {exc}") from exc
    except TypeError as exc:
        raise InvalidInput(f"{where}: {exc}") from exc
    stored = data.get("id")
    if stored is not None and stored != rig.id:
        raise InvalidInput(
            f"{where}: id {stored!r} does not match the content ({rig.id!r}); the numbers were "
            "edited after calibration: delete the id line to accept them"
        )
    return rig


def _keys(table: dict[str, Any], allowed: set[str], where: str) -> None:
    unknown = set(table) - allowed
    if unknown:
        raise InvalidInput(f"{where}: unknown keys {sorted(unknown)}")


def _fmt(value: Any) -> str:
    """TOML literal for numbers and nested lists; floats via repr (exact round trip)."""
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    v = float(value)
    if not math.isfinite(v):
        raise InvalidInput("cannot write a non-finite number to a rig file")
    text = repr(v)
    return text if ("." in text or "e" in text or "inf" in text) else text + ".0"


def _quote(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ") + '"'

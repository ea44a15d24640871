"""A procedural sheet-metal part: a doubly curved panel with a flange, holes,
a character line and an embossing.

The project's own demo and test part, so that nothing depends on external CAD
files. By default the mesh is the outer skin of the part (a single surface,
normals on the visible side), which is what an optical rig above the conveyor
measures. With ``thickness_mm`` it is a closed solid sheet, as the CAD of a
sheet-metal part often is: the same outer skin, an inner skin that far below
it, and the narrow faces joining them along the outline and the holes.

Panel frame: x along the length, y along the width, z up; the origin is the
centre of the panel's footprint at the lower edge of the flange, so the part
rests on the plane z = 0 (on its flange) when placed flat on the conveyor.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .cad import CadModel
from .errors import InvalidInput

if TYPE_CHECKING:
    pass


@dataclass(frozen=True)
class Hole:
    """A hole through the panel: centre (x, y) in mm from the panel centre, radius in mm.

    With ``length_mm`` above the diameter it is a slot of that overall length,
    its long axis turned ``angle_deg`` from the panel's x axis.
    """

    x_mm: float
    y_mm: float
    radius_mm: float
    length_mm: float = 0.0
    angle_deg: float = 0.0

    @property
    def half_axis_mm(self) -> float:
        """Half the distance between a slot's two half circles' centres (0: round)."""
        return max(self.length_mm / 2 - self.radius_mm, 0.0)

    @property
    def reach_mm(self) -> float:
        """How far the hole reaches from its centre."""
        return self.half_axis_mm + self.radius_mm

    def snap(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which points lie inside, and every point inside moved onto the rim along the
        direction from the nearest point of the slot's axis."""
        c, s = np.cos(np.deg2rad(self.angle_deg)), np.sin(np.deg2rad(self.angle_deg))
        dx, dy = x - self.x_mm, y - self.y_mm
        along = c * dx + s * dy
        a = self.half_axis_mm
        foot = np.clip(along, -a, a)
        fx, fy = self.x_mm + c * foot, self.y_mm + s * foot
        r = np.hypot(x - fx, y - fy)
        inside = r < self.radius_mm
        scale = np.where(inside, self.radius_mm / np.maximum(r, 1e-9), 1.0)
        return inside, fx + (x - fx) * scale, fy + (y - fy) * scale


@dataclass(frozen=True)
class PanelSpec:
    """Parameters of the generated panel (all lengths in mm).

    The default is a 600 x 400 mm panel like a small body part. Features are
    placed off-centre on purpose so that the part has no symmetry and a global
    alignment has exactly one answer.
    """

    length_mm: float = 600.0
    width_mm: float = 400.0
    crown_length_mm: float = 14.0
    """Height of the dome along the length (doubly curved with ``crown_width_mm``)."""
    crown_width_mm: float = 8.0
    flange_mm: float = 25.0
    """Depth of the flange that turns down all around the panel."""
    bend_radius_mm: float = 5.0
    character_line_y_mm: float = 70.0
    """Position of the character line (a rounded step running along the length)."""
    character_line_height_mm: float = 3.0
    character_line_radius_mm: float = 4.0
    """Half-width of the rounded step; smaller is sharper."""
    emboss_center_mm: tuple[float, float] = (-130.0, -75.0)
    emboss_size_mm: tuple[float, float] = (140.0, 80.0)
    emboss_height_mm: float = 5.0
    emboss_radius_mm: float = 4.0
    """Half-width of the embossing's rounded edge."""
    holes: tuple[Hole, ...] = field(
        default=(Hole(170.0, 110.0, 16.0), Hole(150.0, -100.0, 10.0), Hole(-200.0, 120.0, 7.0))
    )
    spacing_mm: float = 4.0
    """Mesh spacing on smooth regions."""
    feature_spacing_mm: float = 0.7
    """Mesh spacing across rounded feature edges."""
    thickness_mm: float = 0.0
    """Sheet thickness: 0 for the outer skin only, else a closed solid (see the module notes)."""
    hole_spacing_mm: float = 0.0
    """Mesh spacing across the holes, so that their rims are drawn by short chords (0: the
    smooth regions' spacing, whose chords cut a 10 mm hole's outline by tenths of a mm)."""

    def scaled(self, length_mm: float, width_mm: float) -> PanelSpec:
        """The same design at another size: features move and shrink with the footprint."""
        sx, sy = length_mm / self.length_mm, width_mm / self.width_mm
        s = min(sx, sy)
        return PanelSpec(
            length_mm=length_mm,
            width_mm=width_mm,
            crown_length_mm=self.crown_length_mm * sx,
            crown_width_mm=self.crown_width_mm * sy,
            flange_mm=self.flange_mm,
            bend_radius_mm=self.bend_radius_mm,
            character_line_y_mm=self.character_line_y_mm * sy,
            character_line_height_mm=self.character_line_height_mm,
            character_line_radius_mm=self.character_line_radius_mm,
            emboss_center_mm=(self.emboss_center_mm[0] * sx, self.emboss_center_mm[1] * sy),
            emboss_size_mm=(self.emboss_size_mm[0] * sx, self.emboss_size_mm[1] * sy),
            emboss_height_mm=self.emboss_height_mm,
            emboss_radius_mm=self.emboss_radius_mm,
            holes=tuple(
                Hole(
                    h.x_mm * sx,
                    h.y_mm * sy,
                    max(h.radius_mm * s, 1.5 * self.spacing_mm),
                    h.length_mm * s,
                    h.angle_deg,
                )  # fmt: skip
                for h in self.holes
            ),
            spacing_mm=self.spacing_mm,
            feature_spacing_mm=self.feature_spacing_mm,
            thickness_mm=self.thickness_mm,
            hole_spacing_mm=self.hole_spacing_mm,
        )


@dataclass(frozen=True)
class HoleShift:
    """How far a made part's hole lies from its drawn one: its centre's shift and its radius's
    change, mm (panel frame)."""

    dx_mm: float
    dy_mm: float
    dr_mm: float


def vary_holes(
    spec: PanelSpec,
    rng: np.random.Generator,
    *,
    shift_mm: float = 0.5,
    radius_mm: float = 0.1,
) -> tuple[PanelSpec, tuple[HoleShift, ...]]:
    """The panel as made: each hole shifted by up to ``shift_mm`` in x and y and its radius
    changed by up to ``radius_mm`` (uniform), and the shifts (the truth).

    A hole is made no smaller than its rim can be drawn (1.5 x the spacing across holes):
    a hole drawn at that size only grows, and its shift says by how much."""
    smallest = 1.5 * (spec.hole_spacing_mm if spec.hole_spacing_mm > 0 else spec.spacing_mm)
    holes, shifts = [], []
    for h in spec.holes:
        dx, dy, dr = (float(v) for v in rng.uniform(-1, 1, 3) * [shift_mm, shift_mm, radius_mm])
        radius = h.radius_mm + dr
        if radius < min(smallest, h.radius_mm):
            radius = min(smallest, h.radius_mm)
            dr = radius - h.radius_mm
        length = h.length_mm + 2 * dr if h.length_mm > 0 else 0.0
        holes.append(Hole(h.x_mm + dx, h.y_mm + dy, radius, length, h.angle_deg))
        shifts.append(HoleShift(dx, dy, dr))
    return dataclasses.replace(spec, holes=tuple(holes)), tuple(shifts)


def surface_point(
    spec: PanelSpec, x: float, y: float
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The top surface's point and unit normal (up) at panel coordinates (x, y), mm."""
    e = 1e-3
    z = float(panel_height(spec, np.array([x]), np.array([y]))[0])
    gx = (float(panel_height(spec, np.array([x + e]), np.array([y]))[0]) - z) / e
    gy = (float(panel_height(spec, np.array([x]), np.array([y + e]))[0]) - z) / e
    n = np.array([-gx, -gy, 1.0])
    n /= np.linalg.norm(n)
    return (x, y, z), (float(n[0]), float(n[1]), float(n[2]))


def sheet_metal_panel(spec: PanelSpec | None = None, *, name: str = "panel") -> CadModel:
    """Generate the panel described by ``spec`` as a CAD model.

    Parameters
    ----------
    spec : PanelSpec, optional
        Defaults to ``PanelSpec()``, a 600 x 400 mm panel.
    name : str

    Returns
    -------
    CadModel
        Vertices in mm in the panel frame (see module docstring); face normals
        point to the visible side (up on the top surface, outwards on the flange).
    """
    spec = spec or PanelSpec()
    _validate(spec)
    vertices, faces = _panel_mesh(spec)
    skin = CadModel.from_arrays(vertices, faces, name=name, source=f"<generated {name}>")
    if spec.thickness_mm == 0:
        return skin
    # Thickened from the cleaned skin (the grid's seams merged, slivers dropped).
    vertices, faces = _solid_sheet(skin.vertices, skin.faces, spec.thickness_mm)
    return CadModel.from_arrays(vertices, faces, name=name, source=f"<generated {name}>")


def move_character_line(
    spec: PanelSpec, shift: Callable[[np.ndarray], np.ndarray], *, name: str = "panel"
) -> CadModel:
    """The panel (the outer skin) as made with its character line moved across itself.

    Parameters
    ----------
    spec : PanelSpec, with ``thickness_mm`` 0
    shift : the line's shift along +y at panel x (mm, vectorised), at most
        ``0.3 * character_line_radius_mm`` in size: the step's height is swapped for
        the moved step's on the drawn mesh, whose fine rows follow the drawn line.
    """
    if spec.thickness_mm != 0:
        raise InvalidInput("move_character_line draws the outer skin alone (thickness_mm 0)")
    cad = sheet_metal_panel(spec, name=name)
    v = cad.vertices.copy()
    r, h, yc = (
        spec.character_line_radius_mm,
        spec.character_line_height_mm,
        spec.character_line_y_mm,
    )
    # The top surface near the line: not the flange, which turns down at the ends.
    near = (np.abs(v[:, 1] - yc) < 2 * r) & (
        np.abs(v[:, 0]) < spec.length_mm / 2 - spec.bend_radius_mm
    )
    x, y = v[near, 0], v[near, 1]
    s = np.asarray(shift(x), dtype=np.float64)
    if not (np.all(np.isfinite(s)) and np.abs(s).max(initial=0.0) <= 0.3 * r):
        raise InvalidInput(f"the line's shift must be finite and within {0.3 * r} mm")
    v[near, 2] += h * (_smoothstep((y - yc - s) / r) - _smoothstep((y - yc) / r))
    return CadModel.from_arrays(v, cad.faces, name=name, source=f"<generated {name}>")


def panel_height(spec: PanelSpec, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of the top surface above the flange's lower edge, mm, at panel coordinates."""
    L, W = spec.length_mm, spec.width_mm
    z = (
        spec.flange_mm
        + spec.crown_length_mm * (1.0 - (2.0 * x / L) ** 2)
        + spec.crown_width_mm * (1.0 - (2.0 * y / W) ** 2)
    )
    # Character line: a rounded step (C1 smoothstep) across y = character_line_y_mm.
    z = z + spec.character_line_height_mm * _smoothstep(
        (y - spec.character_line_y_mm) / spec.character_line_radius_mm
    )
    # Embossing: a raised rounded rectangle; its edge is the same smoothstep
    # over the signed distance to the outline.
    d = _rect_distance(x, y, spec.emboss_center_mm, spec.emboss_size_mm)
    z = z + spec.emboss_height_mm * _smoothstep(-d / spec.emboss_radius_mm)
    return z


def _smoothstep(t: np.ndarray) -> np.ndarray:
    """0 below t = -1, 1 above t = 1, a C1 cubic in between."""
    s = np.clip((t + 1.0) * 0.5, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def _rect_distance(x, y, center, size) -> np.ndarray:
    """Signed distance to an axis-aligned rectangle's outline (negative inside)."""
    dx = np.abs(x - center[0]) - size[0] / 2
    dy = np.abs(y - center[1]) - size[1] / 2
    outside = np.hypot(np.maximum(dx, 0.0), np.maximum(dy, 0.0))
    inside = np.minimum(np.maximum(dx, dy), 0.0)
    return outside + inside


def _validate(spec: PanelSpec) -> None:
    L, W = spec.length_mm, spec.width_mm
    positive = {
        "length_mm": L,
        "width_mm": W,
        "flange_mm": spec.flange_mm,
        "bend_radius_mm": spec.bend_radius_mm,
        "character_line_radius_mm": spec.character_line_radius_mm,
        "emboss_radius_mm": spec.emboss_radius_mm,
        "spacing_mm": spec.spacing_mm,
        "feature_spacing_mm": spec.feature_spacing_mm,
    }
    for key, value in positive.items():
        if not np.isfinite(value) or value <= 0:
            raise InvalidInput(f"PanelSpec.{key} must be positive, got {value!r}")
    if not (np.isfinite(spec.hole_spacing_mm) and spec.hole_spacing_mm >= 0):
        raise InvalidInput(f"PanelSpec.hole_spacing_mm must be >= 0, got {spec.hole_spacing_mm!r}")
    t = spec.thickness_mm
    if not np.isfinite(t) or not 0.0 <= t < spec.bend_radius_mm:
        raise InvalidInput(
            f"PanelSpec.thickness_mm must be >= 0 and below bend_radius_mm, got {t!r}"
        )
    if spec.bend_radius_mm >= spec.flange_mm:
        raise InvalidInput("PanelSpec.bend_radius_mm must be smaller than flange_mm")
    if spec.feature_spacing_mm > spec.spacing_mm:
        raise InvalidInput("PanelSpec.feature_spacing_mm must not exceed spacing_mm")
    for h in spec.holes:
        if not (np.isfinite(h.length_mm) and h.length_mm >= 0 and np.isfinite(h.angle_deg)):
            raise InvalidInput(f"hole at ({h.x_mm}, {h.y_mm}): bad length_mm or angle_deg")
        margin = h.reach_mm + 2 * spec.spacing_mm
        # The rim is drawn by the grid's lines across the hole: too few, and it folds.
        rim_spacing = spec.hole_spacing_mm if spec.hole_spacing_mm > 0 else spec.spacing_mm
        if h.radius_mm < 1.5 * rim_spacing:
            raise InvalidInput(
                f"hole radius {h.radius_mm} mm is below 1.5 x the spacing across holes"
            )
        if abs(h.x_mm) + margin > L / 2 or abs(h.y_mm) + margin > W / 2:
            raise InvalidInput(f"hole at ({h.x_mm}, {h.y_mm}) is too close to the panel edge")


_NORMAL_SMOOTHING = 5


def _vertex_sums(faces: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Per vertex, the sum of ``values`` (one row per face) over its faces."""
    out = np.zeros((n, values.shape[1]))
    for k in range(3):
        np.add.at(out, faces[:, k], values)
    return out


def _solid_sheet(
    vertices: np.ndarray, faces: np.ndarray, thickness: float
) -> tuple[np.ndarray, np.ndarray]:
    """The skin made a closed sheet: an inner copy ``thickness`` below it along
    the (smoothed) vertex normals, faces reversed so that normals point out of
    the material, joined to it along the boundary edges by a band of two
    triangles per edge.

    Raises
    ------
    InvalidInput
        A feature bends more tightly than the thickness: some inner face
        would turn over.
    """
    v, f = vertices, faces
    n = len(v)
    tri = v[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # area-weighted
    vn = _vertex_sums(f, fn, n)
    # Normals averaged over a few rings of faces: the embossing's corners are
    # creases, where the inner copy along the raw normals would fold over.
    for _ in range(_NORMAL_SMOOTHING):
        vn /= np.linalg.norm(vn, axis=1, keepdims=True)
        vn = _vertex_sums(f, vn[f].sum(axis=1), n)
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    inner = v - thickness * vn
    itri = inner[f]
    ifn = np.cross(itri[:, 1] - itri[:, 0], itri[:, 2] - itri[:, 0])
    if np.any(np.einsum("ij,ij->i", ifn, fn) <= 0.0):
        raise InvalidInput(
            f"PanelSpec.thickness_mm {thickness} is too large for the panel's tightest bends"
        )
    # Boundary edges (used by one face), directed as in that face: a -> b.
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.minimum(e[:, 0], e[:, 1]) * n + np.maximum(e[:, 0], e[:, 1])
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    a, b = e[counts[inv] == 1].T
    band = np.concatenate([np.stack([b, a, a + n], 1), np.stack([b, a + n, b + n], 1)])
    return np.concatenate([v, inner]), np.concatenate([f, f[:, ::-1] + n, band])


def _axis(
    half: float,
    spacing: float,
    fine: float,
    features: list[tuple[float, float]],
    holes: Sequence[tuple[float, float]] = (),
    hole_spacing: float = 0.0,
) -> np.ndarray:
    """Grid coordinates on [-half, half]: ``spacing`` apart, ``fine`` apart inside feature
    bands, ``hole_spacing`` apart across the holes."""
    n = max(int(np.ceil(2 * half / spacing)), 2)
    coords = [np.linspace(-half, half, n + 1)]
    bands = [(lo, hi, fine) for lo, hi in features] + [(lo, hi, hole_spacing) for lo, hi in holes]
    for lo, hi, step in bands:
        lo, hi = max(lo, -half), min(hi, half)
        if hi > lo:
            coords.append(np.linspace(lo, hi, int(np.ceil((hi - lo) / step)) + 1))
    c = np.unique(np.concatenate(coords))
    # Merge coordinates closer than a fraction of the finest spacing.
    finest = min(fine, hole_spacing) if hole_spacing > 0 else fine
    keep = np.concatenate([[True], np.diff(c) > 0.3 * finest])
    c = c[keep]
    c[0], c[-1] = -half, half
    return c


def _panel_mesh(spec: PanelSpec) -> tuple[np.ndarray, np.ndarray]:
    L, W = spec.length_mm, spec.width_mm
    ex, ey = spec.emboss_center_mm
    sx, sy = spec.emboss_size_mm
    re, rc = 1.3 * spec.emboss_radius_mm, 1.3 * spec.character_line_radius_mm
    hole_x: list[tuple[float, float]] = []
    hole_y: list[tuple[float, float]] = []
    if spec.hole_spacing_mm > 0:
        hole_x = [(h.x_mm - h.reach_mm - 1.5, h.x_mm + h.reach_mm + 1.5) for h in spec.holes]
        hole_y = [(h.y_mm - h.reach_mm - 1.5, h.y_mm + h.reach_mm + 1.5) for h in spec.holes]
    xs = _axis(
        L / 2,
        spec.spacing_mm,
        spec.feature_spacing_mm,
        [(ex - sx / 2 - re, ex - sx / 2 + re), (ex + sx / 2 - re, ex + sx / 2 + re)],
        hole_x,
        spec.hole_spacing_mm,
    )
    ys = _axis(
        W / 2,
        spec.spacing_mm,
        spec.feature_spacing_mm,
        [
            (spec.character_line_y_mm - rc, spec.character_line_y_mm + rc),
            (ey - sy / 2 - re, ey - sy / 2 + re),
            (ey + sy / 2 - re, ey + sy / 2 + re),
        ],
        hole_y,
        spec.hole_spacing_mm,
    )
    nx, ny = len(xs), len(ys)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    px, py = gx.ravel().copy(), gy.ravel().copy()
    idx = np.arange(nx * ny).reshape(nx, ny)

    # Quads of the top surface; quads entirely inside a hole are dropped and
    # the remaining vertices inside a hole are moved radially onto its rim.
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    quads = np.stack([a, b, c, d], axis=1)
    for h in spec.holes:
        inside, px, py = h.snap(px, py)
        quads = quads[~inside[quads].all(axis=1)]
    pz = panel_height(spec, px, py)
    top = np.stack([px, py, pz], axis=1)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    # Drop triangles folded over by the rim snapping (their normal points down).
    t = top[tris]
    nz = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])[:, 2]
    tris = tris[nz > 1e-9]

    # The flange: rings swept outward and down from the top surface's border,
    # a quarter-circle bend of bend_radius_mm then a straight wall.
    loop_vertex, loop_dir = _border_loop(idx, spec)
    rb = spec.bend_radius_mm
    n_bend = 8
    s_bend = np.linspace(0.0, np.pi / 2 * rb, n_bend + 1)[1:]
    # Wall rings end at the flange's lower edge, z = 0, whatever the border's height.
    base = top[loop_vertex]
    m = len(loop_vertex)
    rings = [loop_vertex]
    vertices = [top]
    count = len(top)
    for s in s_bend:
        theta = s / rb
        horiz, drop = rb * np.sin(theta), rb * (1 - np.cos(theta))
        ring = np.column_stack([base[:, :2] + loop_dir * horiz, base[:, 2] - drop])
        vertices.append(ring)
        rings.append(np.arange(count, count + m))
        count += m
    bend_end_z = base[:, 2] - rb
    n_wall = max(int(np.ceil(np.max(bend_end_z) / spec.spacing_mm)), 2)
    for k in range(1, n_wall + 1):
        f = k / n_wall
        ring = np.column_stack([base[:, :2] + loop_dir * rb, bend_end_z * (1 - f)])
        vertices.append(ring)
        rings.append(np.arange(count, count + m))
        count += m
    flange = []
    for r0, r1 in zip(rings[:-1], rings[1:], strict=True):
        a0, b0 = r0, np.roll(r0, -1)
        a1, b1 = r1, np.roll(r1, -1)
        flange.append(np.stack([a0, a1, b1], axis=1))
        flange.append(np.stack([a0, b1, b0], axis=1))
    flange_tris = np.concatenate(flange)
    all_v = np.concatenate(vertices)

    # Orient the flange so that its normals point away from the panel.
    ft = all_v[flange_tris]
    fn = np.cross(ft[:, 1] - ft[:, 0], ft[:, 2] - ft[:, 0])
    centre = ft.mean(axis=1)
    outward = np.einsum("ij,ij->i", fn[:, :2], centre[:, :2])
    if np.sum(outward) < 0:
        flange_tris = flange_tris[:, [0, 2, 1]]
    faces = np.concatenate([tris, flange_tris])
    return all_v, faces


def _border_loop(idx: np.ndarray, spec: PanelSpec) -> tuple[np.ndarray, np.ndarray]:
    """Vertices of the top surface's border, counter-clockwise seen from above,
    with the outward direction of the flange at each; corners get a fan of
    directions so the flange turns round them."""
    nx, ny = idx.shape
    edges = [
        (idx[:, 0], np.array([0.0, -1.0])),  # y = -W/2, x rising
        (idx[-1, :], np.array([1.0, 0.0])),  # x = +L/2, y rising
        (idx[::-1, -1], np.array([0.0, 1.0])),  # y = +W/2, x falling
        (idx[0, ::-1], np.array([-1.0, 0.0])),  # x = -L/2, y falling
    ]
    n_fan = 10
    verts, dirs = [], []
    for i, (edge, normal) in enumerate(edges):
        interior = edge[1:-1]
        verts.append(interior)
        dirs.append(np.repeat(normal[None], len(interior), axis=0))
        nxt = edges[(i + 1) % 4][1]
        a0 = np.arctan2(normal[1], normal[0])
        a1 = np.arctan2(nxt[1], nxt[0])
        if a1 < a0:
            a1 += 2 * np.pi
        angles = np.linspace(a0, a1, n_fan + 1)
        verts.append(np.full(len(angles), edge[-1]))
        dirs.append(np.column_stack([np.cos(angles), np.sin(angles)]))
    return np.concatenate(verts), np.concatenate(dirs)

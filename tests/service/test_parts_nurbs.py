"""A part whose CAD is a STEP of NURBS faces, through the service: configured and uploaded.

The crowned panel of ``bench/bench_nurbs_part.py`` written by our STEP
writer; its tree is built on 20 mm cells, whose chords lie up to 0.14 mm
inside the surface, so that a deviation measured to them and one measured to
the design differ visibly. A comparison point sits at the middle of a cell,
where the chords are farthest from the surface.
"""

from __future__ import annotations

import io
import json
import pickle

import numpy as np
import pytest
from fastapi.testclient import TestClient

from bench.bench_nurbs_part import panel
from inspection import deviations
from inspection.deviations import ComparisonPoint
from inspection.nurbs import tessellate_faces, write_step_surfaces
from service.api import ResultHub, create_app
from service.config import PartSpecBase, load_line_config
from service.models import InspectionResult
from service.parts import PartBundle, PartRegistry, read_nurbs, tree_cache_path
from service.store import DeviationArchive, ResultStore

PART = "crowned"
CELL_MM = 20.0


def cell_middle() -> tuple[list[float], list[float]]:
    """A point of the panel in the middle of one of its 20 mm sampling's cells, and its normal."""
    s = panel()
    model = tessellate_faces([(s, None)], cell_mm=CELL_MM)
    uv = model.corner_params[len(model.cad.faces) // 3].mean(axis=0)
    p, su, sv = s.evaluate(uv[:1], uv[1:], 1)
    n = np.cross(su, sv)[0]
    return [float(x) for x in p[0]], [float(x) for x in n / np.linalg.norm(n)]


@pytest.fixture(scope="module")
def line(tmp_path_factory):
    root = tmp_path_factory.mktemp("nurbs-line")
    parts = root / "configs" / "parts"
    parts.mkdir(parents=True)
    write_step_surfaces(parts / "crowned.step", [panel()])
    pos, n = cell_middle()
    (parts / f"{PART}.toml").write_text(
        f"""name = "{PART}"
cad = "crowned.step"
[tree]
nurbs_cell_mm = {CELL_MM}
[[points]]
name = "mid"
position_mm = {pos}
normal = {n}
lower_mm = -0.05
upper_mm = 0.05
radius_mm = 10.0
"""
    )
    (root / "configs" / "line.toml").write_text(
        f"""
[station]
parts = ["{PART}"]
[storage]
data_dir = "{(root / "data").as_posix()}"
[http]
max_upload_mb = 2.0
"""
    )
    cfg = load_line_config(root / "configs" / "line.toml")
    with PartRegistry.from_config(cfg) as reg:
        reg.preload()
        assert reg.ready(), reg.states()
        yield cfg, reg, parts


@pytest.fixture(scope="module")
def client(line, tmp_path_factory, upload_measurer):
    cfg, reg, _ = line
    d = tmp_path_factory.mktemp("nurbs-api")
    store = ResultStore(d / "results.sqlite")
    app = create_app(
        cfg, store=store, parts=reg, bus=ResultHub(), archive=DeviationArchive(d / "dev"),
        checks={"zenoh": lambda: True}, measurer=upload_measurer,
    )  # fmt: skip
    with TestClient(app) as c:
        yield c
    store.close()


def test_a_configured_step_of_nurbs_faces_is_measured_against_them(client, line):
    cfg, reg, _ = line
    p = client.get(f"/v1/parts/{PART}").json()
    assert (p["state"], p["cad_kind"], p["nurbs_faces"]) == ("ready", "nurbs", 1)
    loaded = reg.get(PART)
    # The tree is cached under a key that holds the faces and their sampling.
    nurbs = loaded.model.nurbs
    path = tree_cache_path(cfg.storage.trees_path(), loaded.cad, loaded.spec, nurbs)
    assert path.is_file()
    assert path != tree_cache_path(cfg.storage.trees_path(), loaded.cad, loaded.spec)


def test_a_cloud_sent_over_rest_is_measured_to_the_design(client, line):
    _, reg, _ = line
    part = reg.get(PART).model
    rng = np.random.default_rng(4)
    s = part.nurbs.surfaces[0]
    uv = rng.uniform(0.0, 1.0, (20_000, 2))
    pts = s.evaluate(uv[:, 0], uv[:, 1])  # on the design: every deviation is 0
    buf = io.BytesIO()
    np.save(buf, pts)
    r = client.post(
        "/v1/inspections",
        files={"file": ("c.npy", buf.getvalue(), "application/octet-stream")},
        data={"part": PART, "frame": "cad"},
    )
    assert r.status_code == 200, r.text
    res = InspectionResult.model_validate(r.json())
    (mid,) = res.comparison
    T = np.asarray(res.transform)
    cad_pts = pts @ T[:3, :3].T + T[:3, 3]
    cps = [ComparisonPoint(c.name, tuple(c.position_mm), tuple(c.normal), c.lower_mm,
                           c.upper_mm, c.radius_mm) for c in reg.get(PART).spec.points]  # fmt: skip
    exact = deviations(part.exact, cad_pts, cps).comparison[0].deviation_mm
    chords = deviations(part.tree, cad_pts, cps).comparison[0].deviation_mm
    assert mid.deviation_mm == pytest.approx(exact, abs=1e-9)
    # The chords lie inside: measured to them, the design itself would be 0.1 mm out.
    assert chords - exact > 0.05


def test_an_uploaded_step_of_nurbs_faces_is_a_nurbs_part_and_a_mesh_is_not(client, line):
    _, reg, parts = line
    step = (parts / "crowned.step").read_bytes()
    spec = {"name": "crowned-up", "tree": {"nurbs_cell_mm": 25.0}}
    r = client.post("/v1/parts", files={"cad": ("door.stp", step)}, data={"spec": json.dumps(spec)})
    assert r.status_code == 202, r.text
    reg.wait(r.headers["location"].rsplit("/", 1)[1], timeout_s=120)
    p = client.get("/v1/parts/crowned-up").json()
    assert (p["state"], p["cad_kind"], p["nurbs_faces"]) == ("ready", "nurbs", 1)
    # Its tree is of its own sampling: another CAD hash than the configured part's.
    assert p["cad_hash"] != client.get(f"/v1/parts/{PART}").json()["cad_hash"]

    buf = io.BytesIO()
    reg.get(PART).cad.to_trimesh().export(buf, file_type="stl")
    r = client.post(
        "/v1/parts",
        files={"cad": ("mesh.stl", buf.getvalue())},
        data={"spec": json.dumps({"name": "crowned-mesh"})},
    )
    assert r.status_code == 202, r.text
    reg.wait(r.headers["location"].rsplit("/", 1)[1], timeout_s=120)
    p = client.get("/v1/parts/crowned-mesh").json()
    assert (p["state"], p["cad_kind"], p["nurbs_faces"]) == ("ready", "mesh", None)


def test_a_step_whose_faces_cannot_be_sampled_is_refused(client, tmp_path):
    bad = b"ISO-10303-21;\nHEADER;\nENDSEC;\nDATA;\n#1 = B_SPLINE_SURFACE_WITH_KNOTS(1);\nENDSEC;\n"
    r = client.post(
        "/v1/parts", files={"cad": ("bad.step", bad)}, data={"spec": json.dumps({"name": "bad"})}
    )
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid_cad" and "bad.step" in err["message"], err
    assert "creating" not in err["message"]  # the client's name, not the staging folder
    assert client.get("/v1/parts/bad").status_code == 404


def test_a_nurbs_part_travels_to_another_host_as_nurbs(line, tmp_path):
    _, reg, _ = line
    part = reg.get(PART)
    bundle = pickle.loads(pickle.dumps(PartBundle.of(part)))  # as Dask ships it
    there = bundle.load(tmp_path / "trees")
    assert there.cad_kind == "nurbs" and there.cad.hash == part.cad.hash
    x = part.cad.vertices[:500] + [0.0, 0.0, 0.3]
    np.testing.assert_array_equal(
        there.model.exact.query(x).distances, part.model.exact.query(x).distances
    )


@pytest.mark.parametrize("unit, nurbs", [("SI_UNIT(.MILLI.,.METRE.)", True),
                                         ("SI_UNIT($,.METRE.)", False)])  # fmt: skip
def test_a_step_in_other_units_than_mm_is_left_to_the_mesh_reader(line, tmp_path, unit, nurbs):
    _, _, parts = line
    text = (parts / "crowned.step").read_text()
    entity = f"#99999 = ( LENGTH_UNIT() NAMED_UNIT(*) {unit} );"
    declared = text.replace("\nENDSEC;\nEND-ISO", f"\n{entity}\nENDSEC;\nEND-ISO")
    assert declared != text
    path = tmp_path / "declared.step"
    path.write_text(declared)
    model = read_nurbs(path, PartSpecBase(name="declared"))
    assert (model is not None) == nurbs

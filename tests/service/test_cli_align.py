"""``inspection align`` and ``inspection check`` end to end, in process.

Both measure through ``inspection.measure.measure_cloud``; these tests hold the
command line to its options, its outputs and its exit codes (0 a usable fit of
a cloud that matches the CAD, or a passing part; 1 a cloud that does not
match, an unusable fit, or a part that fails or cannot be judged; 2 bad input).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from inspection.alignment import sample_facing
from inspection.cad import CadModel
from service.cli import main


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A stepped block (no symmetry seen from above), a cloud of its top side a
    little off the CAD frame, and comparison points on it."""
    d = tmp_path_factory.mktemp("cli")
    base = trimesh.creation.box((120.0, 80.0, 20.0))
    step = trimesh.creation.box((40.0, 30.0, 10.0))
    step.apply_translation([30.0, 15.0, 15.0])
    ramp = trimesh.creation.box((30.0, 20.0, 10.0))
    ramp.apply_transform(trimesh.transformations.rotation_matrix(0.4, [0, 1, 0], [-30, -20, 10]))
    mesh = trimesh.util.concatenate([base, step, ramp])
    stl = d / "block.stl"
    mesh.export(stl)
    cad = CadModel.from_mesh(mesh)
    T = np.eye(4)
    T[:3, :3] = trimesh.transformations.rotation_matrix(0.02, [0.3, 0.2, 1.0])[:3, :3]
    T[:3, 3] = [0.8, -0.5, 0.3]
    pts, _ = sample_facing(cad.vertices, cad.faces, cad.face_normals, T, 20_000, seed=0)
    pts += np.random.default_rng(0).normal(scale=0.02, size=pts.shape)
    cloud = d / "cloud.npy"
    np.save(cloud, pts)
    points = d / "points.json"
    cps = [
        {"name": "base", "position": [-40.0, 25.0, 10.0], "normal": [0, 0, 1], "lower_mm": -0.1,
         "upper_mm": 0.1, "radius_mm": 5.0},
        {"name": "step", "position": [30.0, 15.0, 20.0], "normal": [0, 0, 1], "lower_mm": 0.2,
         "upper_mm": 0.4, "radius_mm": 5.0},
    ]  # fmt: skip
    points.write_text(json.dumps(cps))
    # Points filling a box around the part: no surface of it.
    junk = d / "junk.npy"
    np.save(junk, np.random.default_rng(1).uniform([-100, -80, -30], [100, 80, 60], (5000, 3)))
    return {
        "stl": stl, "cloud": cloud, "points": points, "junk": junk,
        "T_cad_data": np.linalg.inv(T), "dir": d,
    }  # fmt: skip


def test_align_prints_the_transform_as_json(files, capsys):
    code = main(["align", str(files["stl"]), str(files["cloud"]), "--no-global", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert out["converged"] and out["stop_reason"] == "converged"
    assert out["frame"] == "cad" and out["verdict"] == "pass" and out["reason"] is None
    # Seen from above, the block's in-plane position rests on a few vertical
    # edges (the fit reports two weak directions): 20k points with 0.02 mm of
    # noise fix it to ~10 um, its rotation far better.
    T = np.asarray(out["transform"])
    assert np.allclose(T[:3, :3], files["T_cad_data"][:3, :3], atol=1e-3)
    assert np.allclose(T[:3, 3], files["T_cad_data"][:3, 3], atol=0.05)
    assert len(out["degenerate_directions"]) > 0
    assert 0.015 < out["rms_mm"] < 0.025
    # The fit's quality as the service reports it: the weak directions by name,
    # no global search (so no ambiguity and no runner-up).
    q = out["quality"]
    assert len(q["weak_directions"]) == len(out["degenerate_directions"])
    assert all("translation" in w or "rotation" in w for w in q["weak_directions"])
    assert 0 <= q["observability"] < 0.01
    assert q["ambiguous"] is None and q["runner_up_score"] is None
    assert "candidates" not in out
    assert {"read", "part", "align", "total"} <= set(out["timings_ms"])


def test_the_right_cad_matches(files, capsys):
    """The fit's residual against the cloud's own noise: about 1x for the right CAD."""
    code = main(["align", str(files["stl"]), str(files["cloud"]), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    match = out["match"]
    assert match["matches"] is True and match["reason"] is None
    # The cloud's noise is 0.02 mm, estimated without the CAD.
    assert 0.015 < match["noise_mm"] < 0.025
    assert 0.8 < match["residual_ratio"] < 1.5


def test_a_cloud_of_another_shape_does_not_match(files, capsys):
    """A CAD with a 0.3 mm ripple over the whole top: the fit converges, keeps every
    point, stays far under the 1 mm residual a measurement allows, and judges the
    part, yet its residual is ten times the cloud's own noise: align says the
    cloud does not match the CAD, and exits 1."""
    mesh = trimesh.load(files["stl"])
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=2.5)
    v = np.array(v)
    v[:, 2] += 0.3 * np.sin(v[:, 0] / 8.0)
    rippled = files["dir"] / "rippled.stl"
    trimesh.Trimesh(v, f, process=False).export(rippled)
    code = main(["align", str(rippled), str(files["cloud"]), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 1
    assert out["converged"] and out["rms_mm"] < 1.0 and out["inlier_fraction"] > 0.9
    assert out["verdict"] is not None  # the sequence alone would measure from it
    match = out["match"]
    assert match["matches"] is False and match["residual_ratio"] > 5
    assert "the cloud's own noise" in match["reason"]
    code = main(["align", str(rippled), str(files["cloud"])])
    text = capsys.readouterr().out
    assert code == 1
    assert "match: the cloud DOES NOT MATCH the CAD: the fit's residual" in text


def test_too_few_points_kept_do_not_match(files, capsys):
    code = main(["align", str(files["stl"]), str(files["junk"]), "--no-global"])
    text = capsys.readouterr().out
    assert code == 1
    assert "match: the cloud DOES NOT MATCH the CAD: the fit keeps" in text


def test_check_refuses_an_empty_list_of_points(files, capsys):
    """No comparison point leaves nothing to judge the part by: bad input, not a pass."""
    empty = files["dir"] / "none.json"
    empty.write_text("[]")
    code = main(["check", str(files["stl"]), str(files["cloud"]), "--points", str(empty)])
    captured = capsys.readouterr()
    assert code == 2
    assert "PASS" not in captured.out
    assert "no comparison points" in captured.err


def test_align_human_output(files, capsys):
    code = main(
        ["align", str(files["stl"]), str(files["cloud"]), "--no-global", "--loss", "welsch"]
    )
    text = capsys.readouterr().out
    assert code == 0
    assert "T_cad_data" in text and "rms" in text
    assert "fit quality: observability ratio" in text and "weak directions: " in text


def test_global_search_from_a_saved_tree(files, capsys):
    """Without --no-global the pose is searched (frame "data"); a saved tree
    gives the CAD back from the mesh it stores."""
    from inspection.grid import GridTree

    tree = files["dir"] / "block.npz"
    GridTree.build(CadModel.from_mesh(trimesh.load(files["stl"]))).save(tree)
    code = main(["align", str(tree), str(files["cloud"]), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert out["frame"] == "data" and out["ambiguous"] is False
    assert out["quality"]["ambiguous"] is False and len(out["candidates"]) >= 1
    assert np.allclose(np.asarray(out["transform"])[:3, 3], files["T_cad_data"][:3, 3], atol=0.05)


def test_an_unusable_fit_exits_1(files, capsys):
    """A cloud that is not the part: the fit keeps too few points, and says so."""
    code = main(["align", str(files["stl"]), str(files["junk"]), "--no-global", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 1
    assert out["verdict"] is None
    assert "below the 50% required" in out["reason"]
    assert out["inlier_fraction"] < 0.5


def test_check_reports_verdicts_and_writes_ply(files, capsys):
    out_ply = files["dir"] / "dev.ply"
    code = main(
        ["check", str(files["stl"]), str(files["cloud"]), "--points", str(files["points"]),
         "--no-global", "--json", "--write-ply", str(out_ply)]
    )  # fmt: skip
    doc = json.loads(capsys.readouterr().out)
    # "step" expects +0.2..+0.4 mm where the part is nominal: the part fails.
    assert code == 1
    assert doc["verdict"] == "fail"
    assert doc["reason"] == "out of tolerance at step"
    by_name = {c["name"]: c for c in doc["comparison"]}
    assert by_name["base"]["verdict"] == "pass"
    assert by_name["step"]["verdict"] == "fail"
    assert abs(by_name["base"]["deviation_mm"]) < 0.02
    assert doc["field"]["n"] == 20_000
    assert doc["registration"]["converged"] and doc["quality"]["weak_directions"]
    from inspection.cloud_io import read_cloud

    # In the CAD frame: the block's top lies at z = 10 again.
    written = read_cloud(out_ply)
    assert written.shape == (20_000, 3)
    top = written[np.abs(written[:, 2] - 10.0) < 0.5]
    assert len(top) > 1000 and abs(np.median(top[:, 2]) - 10.0) < 0.01


def test_not_measurable_exits_1(files, capsys):
    """Measured, and not passed: the part cannot be judged, which is not a pass."""
    code = main(
        ["check", str(files["stl"]), str(files["cloud"]), "--points", str(files["points"]),
         "--no-global", "--min-support", "100000"]
    )  # fmt: skip
    text = capsys.readouterr().out
    assert code == 1
    assert "part: NOT_MEASURABLE" in text
    assert "reason: not measurable at base" in text


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda f: [str(f["stl"]), str(f["dir"] / "missing.ply")], "no such file"),
        (lambda f: [str(f["dir"] / "missing.stl"), str(f["cloud"])], "no such file"),
        (lambda f: [str(f["points"]), str(f["cloud"])], "unknown CAD format"),
        (lambda f: [str(f["cloud"]), str(f["cloud"])], "unknown CAD format"),
        (lambda f: [str(f["dir"] / "missing.npz"), str(f["cloud"])], "no such tree file"),
        (lambda f: [str(f["stl"]), str(f["cloud"]), "--seen-from-above", "--loss", "cauchy"],
         "plateau"),
    ],
    ids=["cloud-missing", "cad-missing", "cad-json", "cad-npy", "tree-missing", "view-cauchy"],
)  # fmt: skip
def test_bad_input_exits_2(files, capsys, make, message):
    code = main(["align", *make(files)])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_a_tree_of_another_mesh_is_refused(files, capsys):
    """A tree whose stored mesh is not the CAD it names (a tampered file) exits 2."""
    from inspection.grid import GridTree

    good = files["dir"] / "good.npz"
    GridTree.build(CadModel.from_mesh(trimesh.load(files["stl"]))).save(good)
    with np.load(good) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays["meta"].tobytes().decode())
    meta["cad_hash"] = "0" * 64
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    bad = files["dir"] / "bad.npz"
    np.savez(bad, **arrays)
    code = main(["check", str(bad), str(files["cloud"]), "--points", str(files["points"]),
                 "--no-global"])  # fmt: skip
    assert code == 2
    assert "the tree claims CAD 000000000000" in capsys.readouterr().err
    code = main(["align", str(good), str(files["cloud"]), "--no-global", "--scale", "2"])
    assert code == 2
    assert "--scale does not apply" in capsys.readouterr().err


def test_seen_from_above(files, capsys):
    """The flag measures in the rig frame: the global search, with the view
    direction reaching the fit (same pose on this block, whose faces all face
    up or sideways); it needs a loss with a plateau (above), and does not
    combine with --no-global, which measures in the CAD frame."""
    args = ["align", str(files["stl"]), str(files["cloud"]), "--json"]
    code = main([*args, "--seen-from-above"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["converged"] and out["frame"] == "rig"
    assert np.allclose(np.asarray(out["transform"])[:3, 3], files["T_cad_data"][:3, 3], atol=0.05)
    with pytest.raises(SystemExit) as exc:
        main([*args, "--seen-from-above", "--no-global"])
    assert exc.value.code == 2
    assert "not allowed with" in capsys.readouterr().err

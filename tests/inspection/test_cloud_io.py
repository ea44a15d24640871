"""Cloud files: round trips through PLY, XYZ and NPY, trimesh as an
independent PLY reader, and clear errors on bad content."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from inspection.cloud_io import read_cloud, write_ply
from inspection.errors import InvalidInput


@pytest.fixture
def cloud():
    return np.random.default_rng(0).normal(scale=100.0, size=(500, 3))


def test_ply_round_trip_with_scalars(tmp_path, cloud):
    d = np.linspace(-1.0, 1.0, len(cloud))
    path = write_ply(tmp_path / "c.ply", cloud, scalars={"deviation": d})
    assert np.array_equal(read_cloud(path), cloud)
    # An independent reader sees the same points and the scalar field.
    other = trimesh.load(path, process=False)
    assert np.allclose(np.asarray(other.vertices), cloud)
    attrs = other.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    if attrs is not None:
        assert np.allclose(attrs["deviation"], d.astype(np.float32))


def test_ascii_and_big_endian_ply(tmp_path, cloud):
    pc = trimesh.PointCloud(cloud)
    ascii_path = tmp_path / "a.ply"
    ascii_path.write_bytes(pc.export(file_type="ply", encoding="ascii"))
    assert np.allclose(read_cloud(ascii_path), cloud, atol=1e-5)
    header = (
        "ply\nformat binary_big_endian 1.0\ncomment big\nelement vertex 3\n"
        "property float x\nproperty float y\nproperty float z\nproperty uchar red\nend_header\n"
    )
    rec = np.zeros(3, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("red", "u1")])
    rec["x"], rec["y"], rec["z"] = [1, 2, 3], [4, 5, 6], [7, 8, 9]
    big = tmp_path / "b.ply"
    big.write_bytes(header.encode() + rec.tobytes())
    assert np.array_equal(read_cloud(big), [[1, 4, 7], [2, 5, 8], [3, 6, 9]])


@pytest.mark.parametrize("suffix", [".xyz", ".txt", ".csv"])
def test_text_round_trip(tmp_path, cloud, suffix):
    path = tmp_path / f"c{suffix}"
    sep = "," if suffix == ".csv" else " "
    lines = ["# x y z intensity"] + [sep.join(f"{v:.17g}" for v in (*p, 1.0)) for p in cloud]
    path.write_text("\n".join(lines) + "\n")
    assert np.array_equal(read_cloud(path), cloud)


def test_npy_round_trip(tmp_path, cloud):
    np.save(tmp_path / "c.npy", cloud)
    assert np.array_equal(read_cloud(tmp_path / "c.npy"), cloud)
    np.save(tmp_path / "w.npy", np.hstack([cloud, np.ones((len(cloud), 1))]))
    assert np.array_equal(read_cloud(tmp_path / "w.npy"), cloud)
    np.save(tmp_path / "f.npy", cloud.astype(np.float32))
    assert read_cloud(tmp_path / "f.npy").dtype == np.float64


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("nan.npy", np.array([[0.0, np.nan, 1.0]]), "non-finite"),
        ("empty.npy", np.zeros((0, 3)), "no points"),
        ("flat.npy", np.zeros(9), "shape"),
        ("two.npy", np.zeros((5, 2)), "shape"),
        ("text.npy", np.array([["a", "b", "c"]]), "numbers"),
        ("short.xyz", "1 2\n", "three numbers"),
        ("word.xyz", "1 2 x\n", "not a number"),
        ("inf.xyz", "1 2 inf\n", "non-finite"),
        ("empty.xyz", "# nothing\n", "no points"),
        ("bad.ply", b"not a ply", "not a PLY"),
        (
            "cut.ply",
            b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n"
            b"property float x\nproperty float y\nproperty float z\nend_header\n\x00\x00",
            "truncated",
        ),
        (
            "noxyz.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n",
            "x, y, z",
        ),
        ("cloud.las", b"", "unknown cloud format"),
    ],
)
def test_bad_files_raise(tmp_path, name, content, message):
    path = tmp_path / name
    if isinstance(content, np.ndarray):
        np.save(path, content)
    elif isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    with pytest.raises(InvalidInput, match=message):
        read_cloud(path)


def test_missing_file_raises(tmp_path):
    with pytest.raises(InvalidInput, match="no such file"):
        read_cloud(tmp_path / "none.ply")


def test_write_ply_validates(tmp_path, cloud):
    with pytest.raises(InvalidInput):
        write_ply(tmp_path / "x.ply", cloud[:, :2])
    with pytest.raises(InvalidInput):
        write_ply(tmp_path / "x.ply", np.full((3, 3), np.nan))
    with pytest.raises(InvalidInput):
        write_ply(tmp_path / "x.ply", cloud, scalars={"deviation": np.zeros(3)})
    with pytest.raises(InvalidInput):
        write_ply(tmp_path / "x.ply", cloud, scalars={"x": np.zeros(len(cloud))})

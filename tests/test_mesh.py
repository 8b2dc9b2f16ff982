"""Mesh I/O, centring, shuffling and one-line validation errors."""

import numpy as np
import pytest
import trimesh

from aniformer.errors import MeshError
from aniformer.geometry import center_bbox, shuffle_vertices
from aniformer.io.mesh import load_body_mesh, load_mesh, save_mesh, validate_mesh


@pytest.fixture
def sphere():
    m = trimesh.creation.icosphere(subdivisions=1)
    return m.vertices.astype(np.float32), m.faces.astype(np.int64)


@pytest.mark.parametrize("suffix", [".obj", ".ply"])
def test_save_load_round_trip_keeps_order(tmp_path, sphere, suffix):
    verts, faces = sphere
    path = save_mesh(tmp_path / f"m{suffix}", verts, faces)
    v2, f2 = load_mesh(path)
    assert v2.dtype == np.float32 and f2.dtype == np.int64
    np.testing.assert_allclose(v2, verts, atol=1e-6)
    np.testing.assert_array_equal(f2, faces)
    assert [p.name for p in tmp_path.iterdir()] == [f"m{suffix}"]  # no temp file left


def test_quads_are_triangulated(tmp_path):
    (tmp_path / "quad.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    verts, faces = load_mesh(tmp_path / "quad.obj")
    assert verts.shape == (4, 3) and faces.shape == (2, 3)


def test_center_bbox_numpy_and_torch(sphere):
    import torch
    verts = sphere[0] + np.array([3.0, -2.0, 1.0], np.float32)
    for x in (verts, torch.from_numpy(verts)):
        c = center_bbox(x[None])
        np.testing.assert_allclose(np.asarray(c.max(1)[0] if not isinstance(c, np.ndarray) else c.max(1))
                                   + np.asarray(c.min(1)[0] if not isinstance(c, np.ndarray) else c.min(1)),
                                   0, atol=1e-6)


def test_shuffle_keeps_the_same_triangles(sphere):
    verts, faces = sphere
    perm = np.random.default_rng(0).permutation(len(verts))
    v2, f2 = shuffle_vertices(verts, faces, perm)
    tris = lambda v, f: sorted(map(tuple, np.round(v[f].reshape(len(f), -1), 6)))  # noqa: E731
    assert tris(verts, faces) == tris(v2, f2)
    assert not np.array_equal(v2, verts)


@pytest.mark.parametrize("verts,faces,message", [
    (np.zeros((0, 3)), np.zeros((0, 3), int), "empty"),
    (np.array([[0, 0, np.nan], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]), "NaN"),
    (np.eye(3), np.zeros((0, 3), int), "no faces"),
    (np.eye(3), np.array([[0, 1, 3]]), "out of range"),
    (np.eye(4, 3), np.array([[0, 1, 2, 3]]), "triangles"),
])
def test_validation_errors(verts, faces, message):
    with pytest.raises(MeshError, match=message):
        validate_mesh(verts, faces)


def test_bad_files(tmp_path, sphere):
    with pytest.raises(MeshError, match="no such file"):
        load_mesh(tmp_path / "missing.obj")
    (tmp_path / "empty.obj").write_bytes(b"")
    with pytest.raises(MeshError, match="empty"):
        load_mesh(tmp_path / "empty.obj")
    (tmp_path / "garbage.ply").write_bytes(bytes(range(256)) * 10)
    with pytest.raises(MeshError):
        load_mesh(tmp_path / "garbage.ply")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshError):
        load_mesh(tmp_path / "points.obj")
    (tmp_path / "mesh.txt").write_text("hello")
    with pytest.raises(MeshError, match="unsupported"):
        load_mesh(tmp_path / "mesh.txt")
    save_mesh(tmp_path / "big.obj", *sphere)
    with pytest.raises(MeshError, match="exceeds the limit"):
        load_mesh(tmp_path / "big.obj", max_vertices=10)


def test_obj_keeps_every_vertex_in_file_order(tmp_path):
    """trimesh's OBJ loader drops vertices no face uses (even with process=False); ours keeps them."""
    (tmp_path / "loose.obj").write_text("v 9 9 9\nv 0 0 0\nvt 0 0\nv 1 0 0\nv 0 1 0\nv 5 5 5\nf 2/1 3/1 4/1\nf -3 -2 -1\n")
    assert len(trimesh.load(tmp_path / "loose.obj", process=False).vertices) < 5  # what the loader would give
    verts, faces = load_mesh(tmp_path / "loose.obj")
    np.testing.assert_array_equal(verts, [[9, 9, 9], [0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]])
    np.testing.assert_array_equal(faces, [[1, 2, 3], [2, 3, 4]])  # negative indices count back


def test_units_scale_to_metres_and_absurd_coordinates_are_refused(tmp_path):
    (tmp_path / "cm.obj").write_text("v 0 0 0\nv 0 0 170\nv 0 20 0\nf 1 2 3\n")
    assert load_mesh(tmp_path / "cm.obj", unit="cm")[0].max() == pytest.approx(1.7)
    (tmp_path / "km.obj").write_text("v 0 0 0\nv 0 0 1700\nv 0 20 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"reaches 1\.7e\+03 m, beyond ±1,000 m \(wrong --unit\?\)"):
        load_mesh(tmp_path / "km.obj")
    assert load_mesh(tmp_path / "km.obj", unit="mm")[0].max() == pytest.approx(1.7)
    (tmp_path / "bad.obj").write_text("v 0 0 zero\n")
    with pytest.raises(MeshError, match="line 1 is not a valid OBJ 'v' line"):
        load_mesh(tmp_path / "bad.obj")


@pytest.mark.parametrize(("height", "unit"), [(0.45, "m"), (1.7, "m"), (2.9, "m"), (45, "cm"), (170, "cm"),
                                              (290, "cm"), (450, "mm"), (1700, "mm"), (2900, "mm")])
def test_a_body_files_unit_is_the_one_its_size_is_a_humans_in(tmp_path, height, unit):
    """``--unit auto``: a crouching child to a tall adult, in each of m, cm and mm, read in that unit; the
    largest extent counts (a body lying along x, here)."""
    path = tmp_path / "body.obj"
    path.write_text(f"v 0 0 0\nv {height} 0 0\nv 0 {height / 4} 0.1\nf 1 2 3\n")
    vertices, _, read_as = load_body_mesh(path)
    assert read_as[0] == unit
    assert load_body_mesh(path, unit="cm")[2] == ("cm", "--unit")  # a unit given is taken as it is
    assert np.ptp(vertices, axis=0).max() == pytest.approx(height * {"m": 1, "cm": 0.01, "mm": 0.001}[unit])


@pytest.mark.parametrize("height", [0.1, 10, 35, 350, 5000])
def test_a_body_file_of_no_humans_size_in_any_unit_asks_for_the_unit(tmp_path, height):
    path = tmp_path / "body.obj"
    path.write_text(f"v 0 0 0\nv 0 0 {height}\nv 0 0.01 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match=rf"body\.obj: {height:g} units across, a human body's size in none of "
                                        r"m, cm, mm \(0\.4-3\.0 m\): pass --unit"):
        load_body_mesh(path)


OBJ_TEXTS = {  # the numpy reader takes the first five; the rest go line by line, with the same result
    "triangles": "# c\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "blender": "o Body\nv 0 0 0\nv 1 0 0 0.5 0.5 0.5\nv 0 1 0\nvt 0 0\nvn 0 0 1\ns 1\nusemtl skin\nf 1/1/1 2/1/1 3/1/1\n",
    "spaced": "  v\t0  0 0 \r\nv 1.5e0 0 0\r\n\tv 0 -1 0\r\nf 1//1\t2//1  3//1 \r\nf 3 2 1\r\nvt 1 1\r\n",
    "interleaved": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nv 0 0 1\nf 2 3 4\n",
    "zero index": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 2 3\n",
    "quad": "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n",
    "negative": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n",
    "old mac breaks": "v 0 0 0\rv 1 0 0\rv 0 1 0\rf 1 2 3\r",
    "vertical tab": "v 0 0 0\nv\x0b1 0 0\nv 0 1 0\nf 1 2 3\n",
    "non-ascii comment": "# café\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
}


@pytest.mark.parametrize("name", OBJ_TEXTS)
def test_obj_read_by_numpy_matches_reading_line_by_line(tmp_path, name):
    from aniformer.io.mesh import _read_obj_by_line, _read_triangle_obj, read_obj

    path = tmp_path / "m.obj"
    path.write_bytes(OBJ_TEXTS[name].encode())
    taken = _read_triangle_obj(path.read_bytes())
    assert (taken is not None) == (list(OBJ_TEXTS).index(name) < 5)
    for got, expected in zip(read_obj(path), _read_obj_by_line(path), strict=True):
        assert got.dtype == expected.dtype
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("line", ["v 0 0 zero", "v 0 0", "f 1 2 x", "f 1 2 3 4x", "v 0 0 0#c"])
def test_an_obj_line_the_numpy_reader_cannot_take_is_refused_by_its_number(tmp_path, line):
    (tmp_path / "bad.obj").write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\n{line}\nf 1 2 3\n")
    with pytest.raises(MeshError, match=f"line 4 is not a valid OBJ '{line[0]}' line"):
        load_mesh(tmp_path / "bad.obj")

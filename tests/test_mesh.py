"""Mesh I/O, centring, shuffling and one-line validation errors."""

import numpy as np
import pytest
import trimesh

from aniformer.errors import MeshError
from aniformer.geometry import center_bbox, shuffle_vertices
from aniformer.io.mesh import load_mesh, save_mesh, validate_mesh


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

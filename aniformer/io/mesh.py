"""Triangle meshes in and out: trimesh for file formats, numpy arrays everywhere else.

Vertices are `(V, 3)` float32 in metres (z up), faces `(F, 3)` int64. Files with quads or other
polygons are triangulated on load (fanned); anything else that is not a usable triangle mesh is
refused with a one-line `MeshError`. OBJ files are read here, not by trimesh, because trimesh's
OBJ loader drops vertices that no face references (even with ``process=False``): every ``v`` line
is kept, in file order. glTF files are read as a viewer shows them (`aniformer.io.gltf_scene`: skins,
node hierarchies and morph targets as the specification defines them). Files in centimetres or
millimetres are scaled to metres by ``unit``; `load_body_mesh` tells m, cm and mm apart by a body's size.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from aniformer.errors import MeshError
from aniformer.io.files import atomic_path

MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")
_AS_GLTF = ": export it as glTF 2.0 (.glb; Blender: File > Export > glTF 2.0), a clip with its animation"
FORMAT_HINTS = {  # what to do with the formats characters and motion most often come in besides these
    **dict.fromkeys((".fbx", ".dae", ".blend", ".usd", ".usda", ".usdc", ".usdz", ".abc", ".3ds", ".ma", ".mb",
                     ".max", ".c4d"), _AS_GLTF),
    ".bvh": ": a BVH is a skeleton's motion without a mesh; play it on a skinned character in Blender and export "
            "that as an animated glTF 2.0 (.glb)",
    ".npz": ": body-model parameters (AMASS, SMPL) are not meshes; export the posed meshes (OBJ frames or a .glb)",
}
DEFAULT_MAX_VERTICES = 2_000_000
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # metres per file unit
HUMAN_EXTENT = (0.4, 3.0)  # metres: a body's largest extent, a crouching child's to a tall adult's arm span
MAX_COORDINATE = 1e3  # metres; beyond this a mesh is in another unit or broken (the model saturates)


def validate_mesh(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh",
                  max_vertices: int = DEFAULT_MAX_VERTICES) -> None:
    """Raise `MeshError` unless `vertices (V, 3)` and `faces (F, 3)` form a usable triangle mesh."""
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"{name}: vertices must have shape (V, 3), got {tuple(vertices.shape)}")
    if len(vertices) == 0:
        raise MeshError(f"{name}: mesh is empty (no vertices)")
    if len(vertices) > max_vertices:
        raise MeshError(f"{name}: {len(vertices):,} vertices exceeds the limit of {max_vertices:,}")
    if not np.isfinite(vertices).all():
        raise MeshError(f"{name}: vertex coordinates contain NaN or infinity")
    peak = float(np.abs(vertices).max())
    if peak > MAX_COORDINATE:
        raise MeshError(f"{name}: a coordinate reaches {peak:.3g} m, beyond ±{MAX_COORDINATE:,.0f} m (wrong --unit?)")
    if faces.ndim != 2 or len(faces) == 0:
        raise MeshError(f"{name}: mesh has no faces")
    if faces.shape[1] != 3:
        raise MeshError(f"{name}: faces must be triangles, got {faces.shape[1]} vertices per face")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{name}: face index out of range [0, {len(vertices) - 1}]")


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Every ``v`` line of an OBJ in file order (referenced or not), and its faces fanned into triangles."""
    read = _read_triangle_obj(path.read_bytes())
    return read if read is not None else _read_obj_by_line(path)


_OBJ_VERTEX = re.compile(rb"^[ \t]*v[ \t]+(\S+)[ \t]+(\S+)[ \t]+(\S+)", re.M)
_OBJ_TRIANGLE = re.compile(rb"^[ \t]*f" + rb"[ \t]+(\d+)(?:/[^ \t\r\n]*)?" * 3 + rb"[ \t\r]*$", re.M)
_OBJ_V_OR_F = re.compile(rb"^[ \t]*[vf](?:[ \t]|\r?$)", re.M)
_UNUSUAL_SPACES = (b"\x0b", b"\x0c", *(bytes([c]) for c in range(0x1c, 0x20)))  # str.split's, not the patterns'


def _read_triangle_obj(data: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    """`read_obj` by regular expressions and numpy, 2.3x faster, for the common file: ASCII, every ``v`` line
    with three numbers, every ``f`` line a triangle of positive indices. None for anything else, which
    `_read_obj_by_line` reads (or refuses, naming the line)."""
    if not data.isascii() or any(c in data for c in _UNUSUAL_SPACES) or data.count(b"\r") != data.count(b"\r\n"):
        return None
    vertices, triangles = _OBJ_VERTEX.findall(data), _OBJ_TRIANGLE.findall(data)
    if len(vertices) + len(triangles) != len(_OBJ_V_OR_F.findall(data)):
        return None
    try:
        return (np.array(vertices, np.float64).reshape(-1, 3),
                np.fromstring(b" ".join(b" ".join(t) for t in triangles), np.int64, sep=" ").reshape(-1, 3) - 1)
    except ValueError:
        return None


def _read_obj_by_line(path: Path) -> tuple[np.ndarray, np.ndarray]:
    vertices, faces = [], []
    with open(path, encoding="utf-8", errors="replace") as f:
        for number, line in enumerate(f, 1):
            parts = line.split()
            if not parts or parts[0] not in ("v", "f"):
                continue
            try:
                if parts[0] == "v":
                    x, y, z = (float(c) for c in parts[1:4])
                    vertices.append((x, y, z))
                    continue
                corners = [int(p.split("/")[0]) for p in parts[1:]]
            except ValueError:
                raise MeshError(f"{path}: line {number} is not a valid OBJ '{parts[0]}' line") from None
            # 1-based; negative indices count back from the latest vertex; 0 is invalid (-1 is then refused)
            corners = [c - 1 if c > 0 else len(vertices) + c if c < 0 else -1 for c in corners]
            faces += [(corners[0], corners[i], corners[i + 1]) for i in range(1, len(corners) - 1)]
    return np.array(vertices, np.float64).reshape(-1, 3), np.array(faces, np.int64).reshape(-1, 3)


def _read_with_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh  # here, not at the top: a second of start-up that OBJ-only runs and --help never need

    try:
        # process=False keeps the vertex order and count exactly as in the file.
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as e:  # trimesh raises many types for garbage input; all mean "unreadable"
        raise MeshError(f"{path}: cannot read mesh ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{path}: file holds no triangle mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3) if len(mesh.faces) else np.zeros((0, 3), np.int64)
    return vertices, faces


def load_mesh(path: str | os.PathLike, max_vertices: int = DEFAULT_MAX_VERTICES,
              unit: str = "m") -> tuple[np.ndarray, np.ndarray]:
    """Read a mesh file in ``unit`` (m, cm, mm) -> (vertices (V, 3) float32 metres, faces (F, 3) int64), validated."""
    vertices, faces, _ = load_body_mesh(path, max_vertices, unit)
    return vertices, faces


def load_body_mesh(path: str | os.PathLike, max_vertices: int = DEFAULT_MAX_VERTICES,
                   unit: str = "auto") -> tuple[np.ndarray, np.ndarray, tuple[str, str]]:
    """`load_mesh` of a human body's file, and (its unit, why): ``unit`` as given, or for ``"auto"`` the one of
    m, cm and mm in which the body's largest extent is a human's (``HUMAN_EXTENT``; the three ranges do not
    overlap), `MeshError` if none is."""
    vertices, faces = _read_mesh(Path(path))
    read_as = body_unit(vertices, path, unit)
    vertices = vertices * UNITS[read_as[0]]
    validate_mesh(vertices, faces, str(path), max_vertices)
    return vertices.astype(np.float32), faces, read_as


def body_unit(vertices: np.ndarray, path: str | os.PathLike, unit: str = "auto") -> tuple[str, str]:
    """(unit, why) of a body's ``vertices`` in its file's unit: ``unit`` as given, or for ``"auto"`` the one of m,
    cm and mm its largest extent is a human's in (``HUMAN_EXTENT``), `MeshError` if none."""
    if unit != "auto":
        return unit, "--unit"
    extent = float(np.ptp(vertices, axis=0).max()) if len(vertices) else float("nan")
    if not np.isfinite(extent):
        return "m", "not measurable"  # validate_mesh refuses the mesh, naming what is wrong with it
    fitting = [name for name, metres in UNITS.items() if HUMAN_EXTENT[0] <= extent * metres <= HUMAN_EXTENT[1]]
    if not fitting:
        raise MeshError(f"{path}: {extent:.4g} units across, a human body's size in none of m, cm, mm "
                        f"({HUMAN_EXTENT[0]}-{HUMAN_EXTENT[1]} m): pass --unit")
    return fitting[0], f"{extent:.4g} units across: {extent * UNITS[fitting[0]]:.2f} m in {fitting[0]}"


def _read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A mesh file's vertices in its own unit (float64) and faces, or a one-line `MeshError`."""
    if not path.is_file():
        raise MeshError(f"{path}: no such file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        hint = FORMAT_HINTS.get(path.suffix.lower(), "")
        raise MeshError(f"{path}: unsupported mesh format (use one of {', '.join(MESH_SUFFIXES)}){hint}")
    if path.stat().st_size == 0:
        raise MeshError(f"{path}: file is empty")
    try:
        if path.suffix.lower() == ".obj":
            vertices, faces = read_obj(path)
        elif path.suffix.lower() in GLTF_SUFFIXES:
            from aniformer.io.gltf_scene import still_mesh  # it imports this module

            vertices, faces = still_mesh(path)
        else:
            vertices, faces = _read_with_trimesh(path)
    except OSError as e:
        raise MeshError(f"{path}: cannot read mesh ({e.strerror})") from None
    return vertices, faces


def save_mesh(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write a mesh atomically; the format follows the suffix."""
    import trimesh

    path = Path(path)
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=faces, process=False)
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=path.suffix.lstrip(".").lower())
    return path


def write_obj(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """A plain OBJ (v / f lines, 1-based, 6 decimals), written atomically. The vertex lines are built by numpy
    (`_vertex_lines`) and the faces' block is cached per topology: an 18k-vertex frame in ~9 ms on 2 cores, where
    one C-level format of all its numbers took 22."""
    vertex_lines = _vertex_lines(np.asarray(vertices, np.float64).ravel())
    faces = np.ascontiguousarray(faces, np.int64)
    with atomic_path(path) as tmp, open(tmp, "wb") as file:
        file.writelines((b"# aniformer\n", vertex_lines, _face_lines(faces.tobytes())))
    return Path(path)


def write_obj_frames(folder: Path, frames: np.ndarray | str | os.PathLike, faces: np.ndarray,
                     progress: Callable[[int], object] | None = None) -> None:
    """frame_NNNN.obj (at least four digits) in ``folder`` for each of ``frames (T, V, 3)``, by `write_obj`;
    ``frames`` may be the path of a .npy file of them, read a frame at a time (a writer process's input)."""
    if isinstance(frames, np.ndarray):
        _write_obj_frames(Path(folder), len(frames), frames, faces, progress)
        return
    with open(frames, "rb") as file:
        _write_obj_frames(Path(folder), *_npy_frames(file), faces, progress)


def _write_obj_frames(folder: Path, count: int, frames: Iterable[np.ndarray], faces: np.ndarray,
                      progress: Callable[[int], object] | None) -> None:
    digits = max(4, len(str(count - 1)))
    for k, vertices in enumerate(frames):
        write_obj(folder / f"frame_{k:0{digits}d}.obj", vertices, faces)
        if progress is not None:
            progress(1)


def _npy_frames(file: BinaryIO) -> tuple[int, Iterator[np.ndarray]]:
    """(T, the frames one by one) of an open .npy file of ``(T, V, 3)``: read, not memory-mapped, so the reader
    holds one frame and not every page it has seen (0.26 GB for 300 frames of 72k vertices)."""
    major, _ = np.lib.format.read_magic(file)
    read_header = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
    shape, fortran_order, dtype = read_header(file)
    if fortran_order or len(shape) != 3:
        raise ValueError(f"{file.name}: not C-ordered frames (T, V, 3), but {shape}")
    return shape[0], (np.fromfile(file, dtype, count=shape[1] * shape[2]).reshape(shape[1:]) for _ in range(shape[0]))


def _vertex_lines(x: np.ndarray) -> bytes:
    """b"v %.6f %.6f %.6f\\n" for each triple of `x`, byte for byte, as one numpy array of fixed-width fields with
    the unused characters (sign, leading zeros, "v " of y and z) masked out."""
    units = np.abs(x) * 1e6
    if not np.all(units < 2.0**52):  # non-finite, or past the integers float64 holds exactly
        return (("v %.6f %.6f %.6f\n" * (len(x) // 3)) % tuple(x.tolist())).encode()
    for i in np.flatnonzero(np.abs(units - np.floor(units) - 0.5) <= 4e-16 * units):
        units[i] = int(f"{abs(x[i]):.6f}".replace(".", ""))  # a product this near a half: %.6f's exact decimal decides
    np.rint(units, out=units)
    width = len(str(int(units.max(initial=0)) // 1_000_000))
    places = 10.0 ** np.arange(width + 5, -1, -1)  # the whole part's digits, then six decimals
    shifted = units / places[:, None]  # exact in float64, and vectorised where numpy's int64 division is not
    np.floor(shifted, out=shifted)
    shifted[1:] -= 10 * shifted[:-1]
    digits = shifted.astype(np.uint8) + ord("0")
    fields = np.empty((len(x), width + 11), np.uint8)  # "v ", "-", digits, ".", separator
    fields[:, :3] = np.frombuffer(b"v -", np.uint8)
    fields[:, 3:3 + width] = digits[:width].T
    fields[:, 3 + width] = ord(".")
    fields[:, 4 + width:-1] = digits[width:].T
    fields[:, -1] = ord(" ")
    fields[2::3, -1] = ord("\n")
    keep = np.ones(fields.shape, bool)
    keep[1::3, :2] = keep[2::3, :2] = False
    keep[:, 2] = np.signbit(x)
    keep[:, 3:2 + width] = units[:, None] >= places[:width - 1]  # no leading zeros before the units digit
    return fields[keep].tobytes()


@functools.lru_cache(maxsize=4)
def _face_lines(faces: bytes) -> bytes:
    corners = np.frombuffer(faces, np.int64) + 1
    return (("f %d %d %d\n" * (len(corners) // 3)) % tuple(corners.tolist())).encode()


GLTF_SUFFIXES = (".glb", ".gltf")  # y-up by the glTF specification

"""Binary glTF 2.0 (GLB) of an animated mesh: morph-target meshes in chunks, root motion on the node.

``write_glb`` writes the file by hand (trimesh can neither write nor read morph targets): y up, the
clip split into meshes of at most ``FRAMES_PER_MESH`` frames, each a base POSITION plus one morph
target per later frame switched by sparse one-hot weights, the chunk on show picked by its node's
scale, and the root motion on the root node; STEP keys at k / fps and an end key at N / fps.
``read_glb`` reads such a file back in the project's axes. See docs/animate.md for the layout. The
skinned writer (rigged.glb) is ``aniformer.io.rigged_glb``, on this module's buffer and document.
"""

from __future__ import annotations

import base64
import json
import os
import struct
import urllib.parse
from collections.abc import Callable
from pathlib import Path

import numpy as np

from aniformer.io.files import atomic_path

_FLOAT, UINT, USHORT = 5126, 5125, 5123
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
FRAMES_PER_MESH = 256  # frames per mesh by default: WebGL2 guarantees 256 texture-array layers
MAX_MORPH_TARGETS = 2048  # three.js keeps a mesh's morph targets in one texture array; beyond this it freezes
MAX_GLB_BYTES = 2**31 - 1  # browsers (three.js) load a GLB into one ArrayBuffer; the GLB header counts in uint32


GLTF_AXES = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # to_gltf_axes as a rotation matrix


def to_gltf_axes(vertices: np.ndarray) -> np.ndarray:
    """z-up (the project's convention) -> glTF's y-up: (x, y, z) -> (x, z, -y)."""
    return np.stack([vertices[..., 0], vertices[..., 2], -vertices[..., 1]], -1)


def from_gltf_axes(vertices: np.ndarray) -> np.ndarray:
    """glTF's y-up -> z-up: (x, y, z) -> (x, -z, y); the inverse of ``to_gltf_axes``."""
    return np.stack([vertices[..., 0], -vertices[..., 2], vertices[..., 1]], -1)


def mesh_chunks(frames: int, frames_per_mesh: int = FRAMES_PER_MESH) -> list[tuple[int, int]]:
    """[start, end) frame ranges of the meshes a clip is split into."""
    return [(s, min(s + frames_per_mesh, frames)) for s in range(0, frames, frames_per_mesh)]


def glb_size(frames: int, vertices: int, triangles: int, frames_per_mesh: int = FRAMES_PER_MESH) -> int:
    """Binary size of ``write_glb``'s file, without its JSON (a few hundred bytes per frame)."""
    positions = 12 * vertices * (frames + len(mesh_chunks(frames, frames_per_mesh)))
    return positions + 12 * triangles + 32 * frames  # + keys, sparse weights, translations


class GlbBuffer:
    """The GLB's binary chunk and the bufferViews / accessors that point into it."""

    def __init__(self):
        self.blobs: list[np.ndarray | bytes] = []  # written one after another: the binary chunk
        self.views: list[dict] = []
        self.accessors: list[dict] = []
        self.length = 0

    def view(self, data: np.ndarray, target: int | None = None, stride: int | None = None) -> int:
        view = {"buffer": 0, "byteOffset": self.length, "byteLength": data.nbytes}
        view.update({"target": target} if target else {})
        view.update({"byteStride": stride} if stride else {})
        self.blobs.append(np.ascontiguousarray(data))  # kept, not copied to bytes: a 72k x 300 clip's are 0.26 GB
        self.blobs.append(b"\0" * (-data.nbytes % 4))
        self.length += data.nbytes + len(self.blobs[-1])
        self.views.append(view)
        return len(self.views) - 1

    def accessor(self, view: int | None, kind: str, count: int, component: int = _FLOAT, offset: int = 0,
                 bounds: np.ndarray | None = None, **extra) -> int:
        accessor = {"componentType": component, "count": int(count), "type": kind, **extra}
        if view is not None:
            accessor.update(bufferView=view, byteOffset=offset)
        if bounds is not None:  # required on POSITION and animation inputs
            accessor["min"] = np.atleast_2d(bounds).min(0).astype(float).tolist()
            accessor["max"] = np.atleast_2d(bounds).max(0).astype(float).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def array(self, values: np.ndarray, kind: str, bounds: bool = False) -> int:
        """An accessor over a fresh view of float32 ``values`` (animation data)."""
        values = np.asarray(values, np.float32)
        return self.accessor(self.view(values), kind, len(values), bounds=values.reshape(len(values), -1) if bounds else None)

    def sparse_one_hot(self, keys: int, targets: int) -> int:
        """(keys x targets) weights where key j + 1 sets target j to 1 and key 0 none (frame = base):
        stored sparse, so linear in the frames, not quadratic."""
        hot = np.arange(1, keys, dtype=np.uint32)
        index = hot * targets + np.minimum(hot, targets) - 1  # the end key repeats the last frame
        sparse = {"count": len(index),
                  "indices": {"bufferView": self.view(index), "componentType": UINT},
                  "values": {"bufferView": self.view(np.ones(len(index), np.float32))}}
        return self.accessor(None, "SCALAR", keys * targets, sparse=sparse)


def _mesh_and_weights(buf: GlbBuffer, frames: np.ndarray, indices: int, name: str) -> tuple[dict, int | None]:
    """A mesh whose base is ``frames[0]`` with one morph target per later frame (z up, written in glTF's axes), and
    its weights output."""
    base, deltas = to_gltf_axes(frames[0]), frames[1:] - frames[0]
    deltas[..., 1] = deltas[..., 2]  # to_gltf_axes in place, (x, y, z) -> (x, z, -y): no second copy of the clip
    np.subtract(frames[0, :, 1], frames[1:, :, 1], out=deltas[..., 2])  # -y as (-y1) - (-y0): a still vertex's is +0
    position = buf.accessor(buf.view(base, ARRAY_BUFFER), "VEC3", len(base), bounds=base)
    primitive = {"attributes": {"POSITION": position}, "indices": indices, "mode": 4, "material": 0}
    mesh = {"name": name, "primitives": [primitive]}
    if not len(deltas):
        return mesh, None
    view = buf.view(deltas, ARRAY_BUFFER, stride=12)  # several accessors in one view need byteStride
    V = len(base)
    # each target's box corners, per component at once: a (V, 3) min per target was half the GLB's time at 18k vertices
    corners = np.stack([np.stack([deltas[..., c].min(1), deltas[..., c].max(1)], 1) for c in range(3)], 2)
    primitive["targets"] = [{"POSITION": buf.accessor(view, "VEC3", V, offset=k * V * 12, bounds=box)}
                            for k, box in enumerate(corners)]
    mesh["weights"] = [0.0] * len(deltas)
    mesh["extras"] = {"targetNames": [f"frame_{k}" for k in range(1, len(frames))]}
    return mesh, buf.sparse_one_hot(len(frames) + 1, len(deltas))


def _visibility(start: int, end: int, frames: int) -> tuple[list[int], list[float]]:
    """STEP keys (frame numbers) and scales that show a chunk for frames [start, end) only."""
    keys, scales = [0], [1.0 if start == 0 else 0.0]
    if start > 0:
        keys, scales = keys + [start], scales + [1.0]
    if end < frames:
        keys, scales = keys + [end], scales + [0.0]
    return keys + [frames], scales + [scales[-1]]


def write_glb(path: str | os.PathLike, frames: np.ndarray, faces: np.ndarray, fps: float = 30.0,
              name: str = "aniformer", translation: np.ndarray | None = None,
              frames_per_mesh: int = FRAMES_PER_MESH, extras: dict | None = None) -> Path:
    """Write ``frames (N, V, 3)`` (z up, metres) sharing ``faces (F, 3)`` as an animated GLB, atomically.

    glTF is y up: positions are written as (x, z, -y). The clip is split into meshes of at most
    ``frames_per_mesh`` frames (child nodes of one root node ``name``); each has its first frame as
    base and one morph target per later frame, switched by sparse one-hot weights. Only the
    current chunk has scale 1. ``translation (N, 3)`` (z up), if given, animates the root node
    (root motion). Every channel is STEP with keys k / fps and one end key at N / fps, so the clip
    lasts N / fps. See docs/animate.md for the layout.
    """
    frames = checked_frames(frames, fps)  # turned to glTF's axes mesh by mesh (`_mesh_and_weights`): no copy of the clip
    faces = np.ascontiguousarray(faces, np.uint32)
    buf = GlbBuffer()
    indices = buf.accessor(buf.view(faces.ravel(), ELEMENT_ARRAY_BUFFER), "SCALAR", faces.size, UINT,
                           bounds=faces.reshape(-1, 1))
    animation = GltfAnimation(buf, len(frames), fps)
    nodes, meshes = _chunk_nodes(buf, animation, frames, indices, name, frames_per_mesh)
    if translation is not None:
        _animate_root(buf, animation, nodes[0], to_gltf_axes(np.asarray(translation, np.float32)))
    gltf = gltf_document(buf, animation, nodes, meshes, name, fps, extras)
    return write_glb_file(Path(path), gltf, buf.blobs)


def checked_frames(frames: np.ndarray, fps: float) -> np.ndarray:
    frames = np.asarray(frames, np.float32)
    if frames.ndim != 3 or frames.shape[2] != 3 or len(frames) == 0:
        raise ValueError(f"frames must have shape (N, V, 3) with N >= 1, got {frames.shape}")
    if not np.isfinite(frames).all():
        raise ValueError("frames contain NaN or infinity")
    if not 0 < fps < float("inf"):
        raise ValueError(f"fps must be positive, got {fps}")
    return frames


class GltfAnimation:
    """The clip's STEP samplers and channels, keyed at k / fps for frames k = 0 .. N (N: the end key)."""

    def __init__(self, buf: GlbBuffer, frames: int, fps: float):
        self.buf, self.frames = buf, frames
        self.all_times = (np.arange(frames + 1) / fps).astype(np.float32)
        self.time_view = buf.view(self.all_times) if frames > 1 else None  # a single frame has no animation
        self.samplers: list[dict] = []
        self.channels: list[dict] = []

    def add(self, node: int, path: str, keys: list[int] | np.ndarray, output: int) -> None:
        keys = np.asarray(keys)
        if np.array_equal(keys, np.arange(keys[0], keys[-1] + 1)):  # a slice of the shared key times
            times = self.buf.accessor(self.time_view, "SCALAR", len(keys), offset=4 * int(keys[0]),
                                      bounds=self.all_times[keys, None])
        else:
            times = self.buf.array(self.all_times[keys], "SCALAR", bounds=True)
        self.samplers.append({"input": times, "output": output, "interpolation": "STEP"})
        self.channels.append({"sampler": len(self.samplers) - 1, "target": {"node": node, "path": path}})


def _chunk_nodes(buf: GlbBuffer, animation: GltfAnimation, frames: np.ndarray, indices: int, name: str,
                 frames_per_mesh: int) -> tuple[list[dict], list[dict]]:
    """The root node ``name`` and one child node and mesh per chunk of frames, their channels added."""
    N = len(frames)
    chunks = mesh_chunks(N, frames_per_mesh)
    several = len(chunks) > 1
    nodes = [{"name": name, "children": list(range(1, len(chunks) + 1))}]
    meshes = []
    for c, (start, end) in enumerate(chunks):
        label = f"{name}_{start:0{len(str(N))}d}" if several else name
        mesh, weights = _mesh_and_weights(buf, frames[start:end], indices, label)
        nodes.append({"name": label, "mesh": c, **({"scale": [0.0] * 3} if start > 0 else {})})
        meshes.append(mesh)
        if weights is not None:
            animation.add(c + 1, "weights", np.arange(start, end + 1), weights)
        if several:
            keys, scales = _visibility(start, end, N)
            animation.add(c + 1, "scale", keys, buf.array(np.repeat(np.array(scales)[:, None], 3, 1), "VEC3"))
    return nodes, meshes


def _animate_root(buf: GlbBuffer, animation: GltfAnimation, root: dict, moves: np.ndarray) -> None:
    """Root motion on the root node: at ``moves[0]`` (y up), keyed through all of them if the clip moves."""
    root["translation"] = moves[0].astype(float).tolist()
    if animation.frames > 1:
        animation.add(0, "translation", np.arange(animation.frames + 1),
                      buf.array(np.concatenate([moves, moves[-1:]]), "VEC3"))


def gltf_document(buf: GlbBuffer, animation: GltfAnimation, nodes: list[dict], meshes: list[dict], name: str,
              fps: float, extras: dict | None) -> dict:
    """The glTF JSON: one scene of the root node, one material, one animation if anything moves."""
    N = animation.frames
    gltf = {
        "asset": {"version": "2.0", "generator": "aniformer.animate"},
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0], "extras": {"frames": N, "fps": float(fps), **(extras or {})}}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": [_MATERIAL],
        "buffers": [{"byteLength": buf.length}],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
    }
    if animation.channels:  # glTF requires at least one channel per animation
        gltf["animations"] = [{"name": name, "samplers": animation.samplers, "channels": animation.channels,
                               "extras": {"fps": float(fps), "frames": N}}]
    return gltf


_MATERIAL = {"name": "body", "doubleSided": True,
             "pbrMetallicRoughness": {"baseColorFactor": [0.62, 0.70, 0.86, 1.0], "metallicFactor": 0.0,
                                      "roughnessFactor": 0.8}}


def write_glb_file(path: Path, gltf: dict, blobs: list[np.ndarray | bytes]) -> Path:
    """A GLB of the JSON ``gltf`` and the binary chunk ``blobs`` (`GlbBuffer.blobs`: arrays and their padding to
    4 bytes, in order), written atomically."""
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)
    binary = sum(memoryview(blob).nbytes for blob in blobs)
    total = 12 + 8 + len(text) + 8 + binary
    if total > MAX_GLB_BYTES:
        raise ValueError(f"{path.name} would be {total / 2**30:.1f} GiB; glTF clients load at most 2 GiB")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<III", _GLB_MAGIC, 2, total))
        f.write(struct.pack("<II", len(text), _JSON_CHUNK) + text)
        f.write(struct.pack("<II", binary, _BIN_CHUNK))
        for blob in blobs:
            f.write(blob)
    return path


_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_ROW = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def read_document(path: str | os.PathLike) -> tuple[dict, Callable[[int], np.ndarray]]:
    """A glTF's JSON (``.glb``, or ``.gltf`` with embedded or side-by-side buffers) and a function from accessor
    index to its array (rows of ``type``'s components; normalised integers as floats in [0, 1] or [-1, 1];
    strides, sparse values and accessors without data as the glTF 2.0 specification reads them). `ValueError`
    for a file that is not glTF 2.0 or whose data cannot be read."""
    path = Path(path)
    data = path.read_bytes()
    if data[:4] == struct.pack("<I", _GLB_MAGIC):
        magic, version, length = struct.unpack_from("<III", data, 0)
        if version != 2 or length != len(data):
            raise ValueError(f"{path}: not a binary glTF 2.0 file")
        json_len = struct.unpack_from("<I", data, 12)[0]
        gltf = json.loads(data[20:20 + json_len])
        bin_start = 20 + json_len + 8
        chunk = data[bin_start:bin_start + struct.unpack_from("<I", data, 20 + json_len)[0]] if bin_start <= len(data) else b""
    else:
        gltf, chunk = json.loads(data), b""
    if not isinstance(gltf, dict) or not str(gltf.get("asset", {}).get("version", "")).startswith("2."):
        raise ValueError(f"{path}: not a glTF 2.0 file")
    buffers = [_buffer_bytes(path, buffer, chunk) for buffer in gltf.get("buffers", [])]

    def view_array(view_index: int, offset: int, dtype: np.dtype, count: int, row: int) -> np.ndarray:
        view = gltf["bufferViews"][view_index]
        stride = view.get("byteStride") or dtype.itemsize * row
        start = view.get("byteOffset", 0) + offset
        return np.ndarray((count, row), dtype, buffers[view["buffer"]], start, (stride, dtype.itemsize)).copy()

    def accessor(i: int) -> np.ndarray:
        a = gltf["accessors"][i]
        dtype, row = np.dtype(_COMPONENTS[a["componentType"]]), _ROW[a["type"]]
        if "bufferView" in a:
            arr = view_array(a["bufferView"], a.get("byteOffset", 0), dtype, a["count"], row)
        else:
            arr = np.zeros((a["count"], row), dtype)
        if "sparse" in a:
            sparse = a["sparse"]
            index = sparse["indices"]
            rows = view_array(index["bufferView"], index.get("byteOffset", 0),
                              np.dtype(_COMPONENTS[index["componentType"]]), sparse["count"], 1)[:, 0]
            values = sparse["values"]
            arr[rows] = view_array(values["bufferView"], values.get("byteOffset", 0), dtype, sparse["count"], row)
        if a.get("normalized") and dtype.kind in "iu":
            arr = np.maximum(arr / float(np.iinfo(dtype).max), -1.0)
        return arr if a["type"] != "SCALAR" else arr[:, 0]

    return gltf, accessor


def _buffer_bytes(path: Path, buffer: dict, chunk: bytes) -> bytes:
    """A buffer's bytes: the GLB's binary chunk, a base64 data URI, or a file beside ``path`` (never outside
    its folder: a file names no other place to read)."""
    uri = buffer.get("uri")
    if uri is None:
        return chunk
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    folder = path.parent.resolve()
    source = (folder / urllib.parse.unquote(uri)).resolve()
    if folder not in source.parents:
        raise ValueError(f"{path}: buffer {uri!r} is outside the file's folder")
    return source.read_bytes()


def read_glb(path: str | os.PathLike) -> dict:
    """Read back a GLB written by ``write_glb``, in the project's axes (z up).

    -> {"frames" (N, V, 3) world positions, "local" (N, V, 3) before the root translation,
    "translation" (N, 3), "faces", "duration" (the last key time of any channel), "gltf"}.
    """
    gltf, accessor = read_document(path)
    local = []
    for mesh in gltf["meshes"]:  # chunk meshes in frame order
        primitive = mesh["primitives"][0]
        base = accessor(primitive["attributes"]["POSITION"])
        local += [base] + [base + accessor(t["POSITION"]) for t in primitive.get("targets", [])]
    local = from_gltf_axes(np.stack(local))
    root = gltf["nodes"][0]
    translation = np.broadcast_to(from_gltf_axes(np.array(root.get("translation", [0.0, 0.0, 0.0]), np.float32)),
                                  (len(local), 3))
    duration = 0.0
    for animation in gltf.get("animations", []):
        for channel in animation["channels"]:
            sampler = animation["samplers"][channel["sampler"]]
            if channel["target"] == {"node": 0, "path": "translation"}:
                translation = from_gltf_axes(accessor(sampler["output"])[:-1])
            duration = max(duration, float(accessor(sampler["input"])[-1]))
    faces = accessor(gltf["meshes"][0]["primitives"][0]["indices"]).reshape(-1, 3).astype(np.int64)
    return {"frames": local + translation[:, None], "local": local, "translation": np.asarray(translation),
            "faces": faces, "duration": duration, "gltf": gltf}

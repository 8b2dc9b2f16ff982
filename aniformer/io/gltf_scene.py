"""A glTF file's (``.glb``, ``.gltf``) meshes as a viewer shows them: still (``still_mesh``), or in every frame
of its animation (``gltf_clip``).

Characters and motions come as glTF from Blender, Mixamo and three.js: skinned, in node hierarchies, with
morph targets; a motion comes as one animated file as often as as a folder of frames. Both read the file as
the glTF 2.0 specification defines its display: node transforms through the hierarchy, morph-target weights,
and linear blend skinning by the joints' world transforms times their inverse bind matrices (a skinned
mesh's own node transform does not apply: trimesh applies it, and reads a character under a scaled or turned
armature scaled or turned twice). ``gltf_clip`` samples the first animation's node translation, rotation and
scale channels (STEP, LINEAR with slerp, CUBICSPLINE) and weights at a frame rate. The triangles of every
mesh shown are one mesh, in the file's axes and unit; a mesh whose node is scaled to nothing is hidden (how
animation.glb switches its chunks), and the meshes shown must make the same mesh in every frame.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aniformer.errors import MeshError
from aniformer.io.glb import read_document
from aniformer.io.mesh import GLTF_SUFFIXES

HIDDEN_SCALE = 1e-9  # |det| of a node's world matrix below this: scaled to nothing, not shown
TRIANGLES = 4  # glTF's primitive mode; points and lines (0-3) are not a surface and are skipped
# required extensions that change how geometry is stored (KHR_mesh_quantization's are plain accessors here; the
# texture and material ones leave the geometry as it is)
UNREAD_EXTENSIONS = {"KHR_draco_mesh_compression", "EXT_meshopt_compression", "EXT_mesh_gpu_instancing"}
# what a glTF of wrong structure or values raises here (an infinite key time: OverflowError)
MALFORMED = (KeyError, IndexError, TypeError, ValueError, AttributeError, OverflowError)


def _one_line(error: Exception) -> str:
    return f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"


def _malformed_is_mesh_error(read):
    """``read`` of a glTF file (its first argument: the path, or a `GltfClip`) with any error of a malformed file
    as one `MeshError` line."""
    @functools.wraps(read)
    def checked(*args, **kwargs):
        try:
            return read(*args, **kwargs)
        except MALFORMED as e:
            path = args[0].path if isinstance(args[0], GltfClip) else args[0]
            raise MeshError(f"{path}: malformed glTF ({_one_line(e)})") from None
    return checked


@dataclass(frozen=True)
class GltfClip:
    """One animation of a glTF file, sampled at ``fps`` from its first key: ``frames`` frames."""

    path: Path
    index: int  # of the file's animations
    animation: str  # its name, or "animation <index>"
    animations: int  # how many the file has
    fps: float
    frames: int

    def record(self) -> dict:
        """What animation.json says of it."""
        return {"name": self.animation, "index": self.index, "of": self.animations, "fps": self.fps,
                "frames": self.frames}

    @_malformed_is_mesh_error
    def sample(self, count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(vertices ``(N, V, 3)`` float32 in the file's axes and unit, faces ``(F, 3)``) of the first ``count``
        frames (default all)."""
        gltf, accessor = _document(self.path)
        animation = gltf["animations"][self.index]
        start, _ = _time_span(animation, accessor)
        times = start + np.arange(self.frames if count is None else min(count, self.frames)) / self.fps
        return _shown_meshes(self.path, gltf, accessor, animation, times)


@_malformed_is_mesh_error
def still_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(vertices ``(V, 3)`` float64 in the file's axes and unit, faces) of a glTF file's default scene as shown
    without its animation, or a one-line `MeshError`."""
    gltf, accessor = _document(Path(path))
    vertices, faces = _shown_meshes(Path(path), gltf, accessor, None, np.zeros(1))
    return vertices[0].astype(np.float64), faces


@_malformed_is_mesh_error
def gltf_clip(path: str | os.PathLike, fps: float | None = None, animation: str | None = None) -> GltfClip | None:
    """The clip of a glTF file's ``animation`` (its name or index; default the first), sampled at ``fps``
    (default: the rate the file declares in its animation's ``extras``, as animation.glb does, else 30), or None
    if ``path`` is not an animated glTF (`MeshError` if ``animation`` is not one of its animations). A file that
    declares its frame count (animation.glb: ``extras.frames``) keeps it at its own rate; otherwise the clip runs
    from the first key to the last, both included."""
    path = Path(path)
    if path.suffix.lower() not in GLTF_SUFFIXES:
        return None
    gltf, accessor = _document(path)
    animations = gltf.get("animations") or []
    names = _names(animations)
    if animation is None:
        index = 0
    elif animation in names:
        index = names.index(animation)
    elif animation.isdigit() and int(animation) < len(names):
        index = int(animation)
    else:
        raise MeshError(f"{path}: no animation {animation!r}; it has "
                        + (", ".join(repr(n) for n in names) if names else "none"))
    if not animations:
        return None
    chosen = animations[index]
    extras = chosen.get("extras") if isinstance(chosen.get("extras"), dict) else {}
    declared = extras.get("fps")
    declared = declared if isinstance(declared, int | float) and not isinstance(declared, bool) and declared > 0 else None
    start, end = _time_span(chosen, accessor)
    rate = float(fps or declared or 30.0)
    if isinstance(extras.get("frames"), int) and extras["frames"] > 0 and declared and rate == declared:
        frames = extras["frames"]
    else:
        frames = int(np.floor((end - start) * rate + 1e-6)) + 1
    return GltfClip(path, index, names[index], len(animations), rate, frames)


@_malformed_is_mesh_error
def animation_names(path: str | os.PathLike) -> list[str]:
    """The names of a glTF file's animations, in order (``animation <index>`` for an unnamed one)."""
    return _names(_document(Path(path))[0].get("animations") or [])


def _names(animations: list[dict]) -> list[str]:
    return [a.get("name") or f"animation {k}" for k, a in enumerate(animations)]


def _document(path: Path) -> tuple[dict, Callable[[int], np.ndarray]]:
    try:
        gltf, accessor = read_document(path)
    except (OSError, *MALFORMED) as e:
        raise MeshError(f"{path}: cannot read glTF ({_one_line(e)})") from None
    unread = set(gltf.get("extensionsRequired", [])) & UNREAD_EXTENSIONS
    if unread:
        raise MeshError(f"{path}: needs glTF extensions this reader lacks ({', '.join(sorted(unread))}); "
                        "export it without them (e.g. no Draco compression)")
    return gltf, accessor


def _time_span(animation: dict, accessor) -> tuple[float, float]:
    """An animation's first and last key time."""
    times = [accessor(sampler["input"]) for sampler in animation["samplers"]]
    return float(min(t.min() for t in times)), float(max(t.max() for t in times))


def _shown_meshes(path: Path, gltf: dict, accessor, animation: dict | None,
                  times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The meshes shown at ``times`` of ``animation`` (None: still), one mesh per frame: (vertices ``(N, V, 3)``,
    faces)."""
    nodes, order = gltf.get("nodes", []), _scene_order(gltf)
    channels = _channels(animation, accessor, times)
    world = _world_transforms(nodes, order, _local_transforms(gltf, channels, times))
    weights = _morph_weights(gltf, channels, times)
    instances = [n for n in order if "mesh" in nodes[n]]
    shown = np.stack([np.full(len(times), True) if "skin" in nodes[n] else np.abs(np.linalg.det(world[n][:, :3, :3]))
                      > HIDDEN_SCALE for n in instances], 1) if instances else np.zeros((len(times), 0), bool)
    positions = {}  # per mesh node: its positions in the frames it is shown in, its faces
    for column, n in enumerate(instances):
        when = np.flatnonzero(shown[:, column])
        if len(when):
            moved, triangles = _node_positions(path, gltf, accessor, n, [w[when] for w in world],
                                               None if weights[n] is None else weights[n][when])
            positions[n] = (dict(zip(when.tolist(), moved.astype(np.float32))), triangles)  # glTF's precision
    frames, faces = None, None
    for k in range(len(times)):
        on = [n for column, n in enumerate(instances) if shown[k, column]]
        if not on:
            raise MeshError(f"{path}: no mesh is shown at {times[k]:.3f} s of the animation")
        offsets = np.cumsum([0] + [len(positions[n][0][k]) for n in on])
        triangles = np.concatenate([positions[n][1] + offset for n, offset in zip(on, offsets)])
        if faces is None:
            faces = triangles
        elif not np.array_equal(triangles, faces):
            raise MeshError(f"{path}: the meshes shown change at {times[k]:.3f} s of the animation "
                            "(a driving clip is one mesh in every frame)")
        if frames is None:
            frames = np.empty((len(times), offsets[-1], 3), np.float32)
        frames[k] = np.concatenate([positions[n][0][k] for n in on])
    return frames, faces


def _scene_order(gltf: dict) -> list[int]:
    """The nodes of the default scene (else of every root), parents before children."""
    nodes = gltf.get("nodes", [])
    scenes = gltf.get("scenes", [])
    if scenes:
        roots = scenes[gltf.get("scene", 0)].get("nodes", [])
    else:
        children = {c for node in nodes for c in node.get("children", [])}
        roots = [n for n in range(len(nodes)) if n not in children]
    order, seen, stack = [], set(), list(reversed(roots))
    while stack:
        n = stack.pop()
        if n in seen:  # the specification's nodes form trees; this file's would be walked forever
            raise ValueError(f"node {n} is reached twice: the node hierarchy is not a tree")
        order.append(n)
        seen.add(n)
        stack.extend(reversed(nodes[n].get("children", [])))
    return order


def _channels(animation: dict | None, accessor, times: np.ndarray) -> dict[tuple[int, str], np.ndarray]:
    """{(node, path): its values at ``times``} of an animation's channels (none for None)."""
    sampled = {}
    for channel in (animation or {}).get("channels", []):
        target = channel["target"]
        if "node" not in target:
            continue
        sampler = animation["samplers"][channel["sampler"]]
        keys = accessor(sampler["input"])
        sampled[target["node"], target["path"]] = _sample(keys, accessor(sampler["output"]),
                                                          sampler.get("interpolation", "LINEAR"), times,
                                                          target["path"] == "rotation")
    return sampled


def _local_transforms(gltf: dict, channels: dict, times: np.ndarray) -> list[np.ndarray]:
    """Per node, its local matrix at each time ``(N, 4, 4)``: its TRS with the animated channels sampled."""
    nodes = gltf.get("nodes", [])
    trs = [{"translation": np.array(node.get("translation", [0.0, 0.0, 0.0]), np.float64),
            "rotation": np.array(node.get("rotation", [0.0, 0.0, 0.0, 1.0]), np.float64),
            "scale": np.array(node.get("scale", [1.0, 1.0, 1.0]), np.float64)} for node in nodes]
    animated = [{path: channels[n, path] for path in ("translation", "rotation", "scale") if (n, path) in channels}
                for n in range(len(nodes))]
    matrices = []
    for node, fixed, moving in zip(nodes, trs, animated):
        if "matrix" in node and not moving:
            matrices.append(np.broadcast_to(np.array(node["matrix"], np.float64).reshape(4, 4).T, (len(times), 4, 4)))
            continue
        parts = {name: moving.get(name, np.broadcast_to(value, (len(times), len(value)))) for name, value in fixed.items()}
        m = np.zeros((len(times), 4, 4))
        m[:, :3, :3] = _quaternion_matrices(parts["rotation"]) * parts["scale"][:, None, :]
        m[:, :3, 3], m[:, 3, 3] = parts["translation"], 1.0
        matrices.append(m)
    return matrices


def _world_transforms(nodes: list[dict], order: list[int], local: list[np.ndarray]) -> list[np.ndarray]:
    """Per node, its world matrix at each time: its parents' (``order``: parents first) times its own."""
    world = list(local)
    for n in order:
        for child in nodes[n].get("children", []):
            world[child] = world[n] @ local[child]
    return world


def _morph_weights(gltf: dict, channels: dict, times: np.ndarray) -> list[np.ndarray | None]:
    """Per node, its morph-target weights at each time ``(N, K)`` (animated, else the node's, else the mesh's)."""
    nodes, meshes = gltf.get("nodes", []), gltf.get("meshes", [])
    weights = []
    for n, node in enumerate(nodes):
        fixed = node.get("weights", meshes[node["mesh"]].get("weights") if "mesh" in node else None)
        if (n, "weights") in channels:
            weights.append(channels[n, "weights"])
        else:
            weights.append(None if fixed is None else np.broadcast_to(np.array(fixed, np.float64), (len(times), len(fixed))))
    return weights


def _node_positions(path: Path, gltf: dict, accessor, n: int, world: list[np.ndarray], weights: np.ndarray | None):
    """(world positions ``(N, V, 3)`` of node ``n``'s triangle primitives at each time, their faces)."""
    node = gltf["nodes"][n]
    vertices, faces, offset = [], [], 0
    for primitive in gltf["meshes"][node["mesh"]]["primitives"]:
        mode = primitive.get("mode", TRIANGLES)
        if mode < TRIANGLES:
            continue
        if mode != TRIANGLES:
            raise MeshError(f"{path}: glTF mesh {node['mesh']} has triangle strips or fans (mode {mode}); only triangle "
                            "lists are read: export with triangulated faces")
        base = accessor(primitive["attributes"]["POSITION"]).astype(np.float64)  # required: else malformed
        targets = [accessor(t["POSITION"]) if "POSITION" in t else np.zeros_like(base) for t in primitive.get("targets", [])]
        local = np.broadcast_to(base, (len(world[n]), *base.shape))
        if targets and weights is not None:
            local = local + np.einsum("tk,kvc->tvc", weights[:, : len(targets)], np.stack(targets))
        if "skin" in node:
            moved = _skinned(gltf, accessor, gltf["skins"][node["skin"]], primitive["attributes"], local, world)
        else:
            moved = local @ world[n][:, :3, :3].transpose(0, 2, 1) + world[n][:, None, :3, 3]
        index = accessor(primitive["indices"]).astype(np.int64) if "indices" in primitive else np.arange(len(base))
        vertices.append(moved)
        faces.append(index.reshape(-1, 3) + offset)
        offset += len(base)
    if not vertices:
        return np.zeros((len(world[n]), 0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(vertices, 1), np.concatenate(faces)


def _skinned(gltf: dict, accessor, skin: dict, attributes: dict, local: np.ndarray, world: list[np.ndarray]) -> np.ndarray:
    """Linear blend skinning of ``local (N, V, 3)`` by the skin's joints at each time."""
    joints = skin["joints"]
    inverse_bind = (accessor(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
                    if "inverseBindMatrices" in skin else np.broadcast_to(np.eye(4), (len(joints), 4, 4)))
    sets = [k for k in range(8) if f"JOINTS_{k}" in attributes]
    bones = np.concatenate([accessor(attributes[f"JOINTS_{k}"]).astype(np.int64) for k in sets], 1)
    weights = np.concatenate([accessor(attributes[f"WEIGHTS_{k}"]) for k in sets], 1)
    weights = weights / np.maximum(weights.sum(1, keepdims=True), 1e-12)
    moved = np.empty_like(local)
    for k in range(len(local)):
        skinning = np.stack([world[j][k] for j in joints]) @ inverse_bind  # (J, 4, 4)
        blended = np.einsum("vi,virc->vrc", weights, skinning[bones])
        moved[k] = np.einsum("vrc,vc->vr", blended[:, :3, :3], local[k]) + blended[:, :3, 3]
    return moved


def _sample(keys: np.ndarray, values: np.ndarray, interpolation: str, times: np.ndarray, rotation: bool) -> np.ndarray:
    """A sampler's values at ``times`` (held before the first key and after the last), as glTF interpolates."""
    values = np.asarray(values, np.float64).reshape(len(keys) * (3 if interpolation == "CUBICSPLINE" else 1), -1)
    if interpolation == "CUBICSPLINE":
        in_tangent, points, out_tangent = values[0::3], values[1::3], values[2::3]
    else:
        points = values
    # keys are float32: a frame sampled at a key's time in float64 may fall a hair before it (STEP: a frame late)
    i = np.clip(np.searchsorted(keys, times + 1e-6 * (1 + np.abs(times)), side="right") - 1, 0, len(keys) - 1)
    j = np.minimum(i + 1, len(keys) - 1)
    span = keys[j] - keys[i]
    s = np.where(span > 0, np.clip((times - keys[i]) / np.where(span > 0, span, 1.0), 0.0, 1.0), 0.0)[:, None]
    if interpolation == "STEP":
        out = points[i]
    elif interpolation == "CUBICSPLINE":
        d = span[:, None]
        out = ((2 * s**3 - 3 * s**2 + 1) * points[i] + (s**3 - 2 * s**2 + s) * d * out_tangent[i]
               + (-2 * s**3 + 3 * s**2) * points[j] + (s**3 - s**2) * d * in_tangent[j])
    elif rotation:
        out = _slerp(points[i], points[j], s)
    else:
        out = (1 - s) * points[i] + s * points[j]
    if rotation:
        out = out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    return out


def _slerp(a: np.ndarray, b: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions, the shorter way round."""
    dot = (a * b).sum(1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot).clip(max=1.0)
    angle = np.arccos(dot)
    sine = np.sin(angle)
    close = sine < 1e-6
    wa = np.where(close, 1 - s, np.sin((1 - s) * angle) / np.where(close, 1.0, sine))
    wb = np.where(close, s, np.sin(s * angle) / np.where(close, 1.0, sine))
    return wa * a + wb * b


def _quaternion_matrices(q: np.ndarray) -> np.ndarray:
    """``(N, 4)`` unit quaternions (x, y, z, w), glTF's order, to ``(N, 3, 3)`` rotation matrices."""
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    x, y, z, w = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                     2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                     2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)

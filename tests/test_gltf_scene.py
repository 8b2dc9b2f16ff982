"""glTF read as a viewer shows it (aniformer/io/gltf_scene.py): skins, node hierarchies, morph targets, and
animations sampled as the specification interpolates them."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import scipy.spatial
import trimesh

from aniformer.errors import MeshError
from aniformer.io.glb import from_gltf_axes, write_glb
from aniformer.io.gltf_scene import gltf_clip, still_mesh
from aniformer.io.mesh import load_mesh

ROOT = Path(__file__).resolve().parents[1]
BLENDER = shutil.which("blender")
TRIANGLE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], np.float32)


def triangle_gltf(folder: Path, channels: list[tuple[str, str, list[float], list[float]]], *, uri: str | None = None,
                  node: dict | None = None, extra: dict | None = None) -> Path:
    """A .gltf of one triangle on a node animated by ``channels`` ((path, interpolation, key times, flat
    values)), its buffer in ``folder/tri.bin`` (or at ``uri``, or a data URI for ``uri="data"``)."""
    blobs = [TRIANGLE.tobytes(), np.array([0, 1, 2], np.uint32).tobytes()]
    views, accessors = [], [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                             "min": [0, 0, 0], "max": [1, 1, 0]},
                            {"bufferView": 1, "componentType": 5125, "count": 3, "type": "SCALAR"}]
    samplers, anim_channels = [], []
    for path, interpolation, times, values in channels:
        blobs += [np.array(times, np.float32).tobytes(), np.array(values, np.float32).tobytes()]
        row = {"translation": "VEC3", "scale": "VEC3", "rotation": "VEC4"}[path]
        per_key = 3 if interpolation == "CUBICSPLINE" else 1
        accessors += [{"bufferView": len(blobs) - 2, "componentType": 5126, "count": len(times), "type": "SCALAR",
                       "min": [min(times)], "max": [max(times)]},
                      {"bufferView": len(blobs) - 1, "componentType": 5126, "count": per_key * len(times), "type": row}]
        samplers.append({"input": len(accessors) - 2, "output": len(accessors) - 1, "interpolation": interpolation})
        anim_channels.append({"sampler": len(samplers) - 1, "target": {"node": 0, "path": path}})
    offset = 0
    for blob in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        offset += len(blob)
    data = b"".join(blobs)
    if uri == "data":
        buffer = {"byteLength": len(data), "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}
    else:
        (folder / (uri or "tri.bin")).write_bytes(data)
        buffer = {"byteLength": len(data), "uri": uri or "tri.bin"}
    gltf = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0, **(node or {})}], "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
            "buffers": [buffer], "bufferViews": views, "accessors": accessors, **(extra or {})}
    if channels:
        gltf["animations"] = [{"name": "move", "samplers": samplers, "channels": anim_channels}]
    path = folder / "tri.gltf"
    path.write_text(json.dumps(gltf))
    return path


def test_linear_rotation_is_slerped_and_translation_lerped(tmp_path):
    quarter = [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]  # 90 degrees about z
    path = triangle_gltf(tmp_path, [("rotation", "LINEAR", [0.0, 1.0], [0, 0, 0, 1, *quarter]),
                                    ("translation", "LINEAR", [0.0, 1.0], [0, 0, 0, 2, 0, 0])])
    clip = gltf_clip(path, fps=4)
    assert (clip.frames, clip.fps, clip.animation) == (5, 4.0, "move")  # 0, 0.25 ... 1 s, both ends
    frames, faces = clip.sample()
    half = frames[2]  # 0.5 s: 45 degrees, 1 m along x
    angle = np.pi / 4
    np.testing.assert_allclose(half[1], [1 + np.cos(angle), np.sin(angle), 0], atol=1e-6)
    np.testing.assert_array_equal(faces, [[0, 1, 2]])


def test_step_holds_and_cubic_spline_follows_its_tangents(tmp_path):
    # translation x: a Hermite curve from 0 to 1 over 2 s, out-tangent 1 per second at the first key, in-tangent 0
    # at the last; (in-tangent, value, out-tangent) per key
    cubic = [0, 0, 0, 0, 0, 0, 1, 0, 0] + [0, 0, 0, 1, 0, 0, 0, 0, 0]
    path = triangle_gltf(tmp_path, [("translation", "CUBICSPLINE", [0.0, 2.0], cubic),
                                    ("scale", "STEP", [0.0, 1.0], [1, 1, 1, 3, 3, 3])], uri="data")
    frames, _ = gltf_clip(path, fps=2).sample()
    s = np.arange(5) / 4  # 0, 0.5 ... 2 s over a key span of 2 s
    hermite = (s**3 - 2 * s**2 + s) * 2.0 * 1.0 + (-2 * s**3 + 3 * s**2) * 1.0
    np.testing.assert_allclose(frames[:, 0, 0], hermite, atol=1e-6)
    np.testing.assert_allclose(frames[:, 1, 0] - frames[:, 0, 0], [1, 1, 3, 3, 3], atol=1e-6)  # STEP: 3 from 1 s on


def test_still_mesh_reads_node_transforms_and_external_buffers(tmp_path):
    path = triangle_gltf(tmp_path, [], node={"translation": [0, 0, 5], "scale": [2, 2, 2]},
                         extra={"extensionsRequired": ["KHR_texture_basisu"]})  # textures: the geometry reads as is
    vertices, _ = still_mesh(path)
    np.testing.assert_allclose(vertices, TRIANGLE * 2 + [0, 0, 5])
    assert gltf_clip(path) is None  # no animation: not a clip


@pytest.mark.parametrize("case, message", [
    ("outside", "outside the file's folder"),
    ("cycle", "malformed glTF (ValueError: node 0 is reached twice: the node hierarchy is not a tree)"),
    ("no such mesh", "malformed glTF (IndexError"),
    ("draco", "needs glTF extensions this reader lacks (KHR_draco_mesh_compression)"),
])
def test_refused_files_say_why_in_one_line(tmp_path, case, message):
    inner = tmp_path / "inner"
    inner.mkdir()
    if case == "outside":  # a file may name no place to read beyond its own folder
        (tmp_path / "secret.bin").write_bytes(b"\0" * 64)
        path = triangle_gltf(inner, [])
        gltf = json.loads(path.read_text())
        gltf["buffers"][0]["uri"] = "../secret.bin"
        path.write_text(json.dumps(gltf))
    elif case in ("cycle", "no such mesh"):
        path = triangle_gltf(inner, [], node={"children": [0]} if case == "cycle" else {"mesh": 7})
    else:  # a texture compression required beside it changes nothing of the geometry
        required = ["KHR_draco_mesh_compression", "KHR_texture_basisu"]
        path = triangle_gltf(inner, [], extra={"extensionsRequired": required, "extensionsUsed": required})
    with pytest.raises(MeshError, match=message.replace("(", r"\(").replace(")", r"\)")) as caught:
        load_mesh(path)
    assert "\n" not in str(caught.value)


def test_animation_glb_reads_back_frame_for_frame_across_its_chunks(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.normal(size=(20, 10, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 7], [7, 8, 9]])
    path = write_glb(tmp_path / "c.glb", frames, faces, fps=25, frames_per_mesh=8,
                     translation=np.cumsum(rng.normal(size=(20, 3)), 0).astype(np.float32) * 0.1)
    clip = gltf_clip(path)
    assert (clip.frames, clip.fps) == (20, 25.0)  # its own count and rate, not the end key's extra frame
    read, read_faces = clip.sample()
    from aniformer.io.glb import read_glb

    np.testing.assert_allclose(from_gltf_axes(read), read_glb(path)["frames"], atol=1e-5)
    np.testing.assert_array_equal(read_faces, faces)
    assert still_mesh(path)[0].shape == (10, 3)  # the chunks scaled to nothing are not shown


@pytest.mark.skipif(BLENDER is None, reason="no blender on PATH (.ci/run installs Debian's blender)")
def test_a_blender_skinned_clip_reads_as_blender_plays_it(tmp_path):
    """Skinning under a moving, turned, scaled armature, a shape key, a box parented to a bone: one animation."""
    glb, played = tmp_path / "tube.glb", tmp_path / "tube.npy"
    proc = subprocess.run([BLENDER, "-b", "--factory-startup", "--python-exit-code", "1", "--python",
                           str(ROOT / "bench" / "blender_skinned_clip.py"), "--", str(glb), str(played)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    blender = np.load(played)  # (25, V, 3), z up
    clip = gltf_clip(glb, fps=24)
    assert clip.frames == len(blender)
    frames, _ = clip.sample()
    frames = from_gltf_axes(frames)
    _, same = scipy.spatial.cKDTree(blender[0]).query(frames[0])  # the exporter splits vertices at flat faces
    error = np.linalg.norm(frames - blender[:, same], axis=-1)
    moved = np.linalg.norm(blender - blender[:1], axis=-1).max()
    assert moved > 0.5 and error.max() < 1e-4, (moved, error.max(1))
    assert clip.animation == "bend" and frames.shape[1] > 744  # the tube's split vertices and the hat's
    # still, as shown before playing: the first frame's pose, 1.26 m tall with the hat (the armature's 1.2
    # scale applied once); trimesh applied it twice to the skinned tube (1.44 m) and placed the hat elsewhere
    still = from_gltf_axes(still_mesh(glb)[0])
    np.testing.assert_allclose(still, frames[0], atol=1e-6)
    assert np.ptp(still[:, 2]) == pytest.approx(1.26, abs=1e-4)
    assert np.ptp(from_gltf_axes(np.asarray(trimesh.load(glb, force="mesh").vertices))[:, 2]) == pytest.approx(1.44, abs=1e-3)


def test_an_animation_is_chosen_by_name_or_index(tmp_path):
    path = triangle_gltf(tmp_path, [("translation", "LINEAR", [0.0, 1.0], [0, 0, 0, 2, 0, 0])])
    gltf = json.loads(path.read_text())
    held = json.loads(json.dumps(gltf["animations"][0]))
    held["name"], held["samplers"][0]["interpolation"] = "held", "STEP"  # the same keys, held
    gltf["animations"].append(held)
    path.write_text(json.dumps(gltf))
    at_half = {choice: gltf_clip(path, fps=2, animation=choice).sample()[0][1, 0, 0] for choice in (None, "held", "1")}
    assert at_half == pytest.approx({None: 1.0, "held": 0.0, "1": 0.0})
    assert gltf_clip(path, animation="held").record() == {"name": "held", "index": 1, "of": 2, "fps": 30.0,
                                                          "frames": 31}
    with pytest.raises(MeshError, match="no animation 'run'; it has 'move', 'held'"):
        gltf_clip(path, animation="run")

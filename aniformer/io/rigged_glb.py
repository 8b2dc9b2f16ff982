"""Binary glTF 2.0 (GLB) of a skinned mesh: ``write_rigged_glb`` writes a rig (``aniformer.rig``) and its
clip as joint motion (rigged.glb), with ``aniformer.io.glb``'s buffer, animation and document. See
docs/animate.md for the layout.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from aniformer.io.glb import (
    ARRAY_BUFFER,
    ELEMENT_ARRAY_BUFFER,
    GLTF_AXES,
    UINT,
    USHORT,
    GlbBuffer,
    GltfAnimation,
    checked_frames,
    gltf_document,
    to_gltf_axes,
    write_glb_file,
)


def write_rigged_glb(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, rig, motion,
                     fps: float = 30.0, name: str = "aniformer", extras: dict | None = None) -> Path:
    """Write a skinned mesh and its clip as a GLB, atomically: ``vertices (V, 3)`` (z up, metres: the bind
    pose) and ``faces``, ``rig`` (``aniformer.rig.Rig``: joints, bind transforms, 4 weights per vertex) and
    ``motion`` (``aniformer.rig_motion.RigMotion``). y up; the mesh node (``name``) and the skeleton's root joint
    are the scene's two roots; each joint that turns keys its local rotation at every frame and the root joint its
    translation, STEP at k / fps plus an end key at N / fps, as ``write_glb``'s clip. No morph targets."""
    frames = len(motion.rotations)
    checked_frames(motion.root[:, None], fps)
    turn = np.eye(4)
    turn[:3, :3] = GLTF_AXES
    local = turn @ rig.local_bind @ turn.T
    buf = GlbBuffer()
    bind = to_gltf_axes(np.asarray(vertices, np.float32))
    attributes = {"POSITION": buf.accessor(buf.view(bind, ARRAY_BUFFER), "VEC3", len(bind), bounds=bind),
                  "JOINTS_0": buf.accessor(buf.view(np.ascontiguousarray(rig.joints, np.uint16), ARRAY_BUFFER),
                                           "VEC4", len(bind), USHORT),
                  "WEIGHTS_0": buf.accessor(buf.view(np.ascontiguousarray(rig.weights, np.float32), ARRAY_BUFFER),
                                            "VEC4", len(bind))}
    faces = np.ascontiguousarray(faces, np.uint32)
    indices = buf.accessor(buf.view(faces.ravel(), ELEMENT_ARRAY_BUFFER), "SCALAR", faces.size, UINT,
                           bounds=faces.reshape(-1, 1))
    inverse_bind = (turn @ rig.inverse_bind @ turn.T).astype(np.float32)
    inverse_bind[:, 3] = [0, 0, 0, 1]  # exactly affine, as glTF requires
    skin = {"joints": list(range(1, len(rig.names) + 1)), "skeleton": 1,
            "inverseBindMatrices": buf.accessor(buf.view(np.swapaxes(inverse_bind, 1, 2)), "MAT4", len(rig.names))}
    from scipy.spatial.transform import Rotation  # here: a quarter second of imports no other job needs

    turns = Rotation.from_quat(motion.rotations.reshape(-1, 4)).as_matrix().reshape(*motion.rotations.shape[:-1], 3, 3)
    rotations = _quaternions(GLTF_AXES @ turns @ GLTF_AXES.T)  # (N, J, 4)
    root = to_gltf_axes(np.asarray(motion.root, np.float32))
    nodes = [{"name": name, "mesh": 0, "skin": 0}]
    for j, label in enumerate(rig.names):  # at rest: the first frame, as write_glb's file shows it
        nodes.append({"name": label, "translation": (root[0] if j == 0 else local[j, :3, 3]).tolist(),
                      "rotation": rotations[0, j].tolist()})
    for j, parent in enumerate(rig.parents):
        if parent >= 0:
            nodes[parent + 1].setdefault("children", []).append(j + 1)
    animation = GltfAnimation(buf, frames, fps)
    if frames > 1:
        keys = np.arange(frames + 1)
        for j in range(len(rig.names)):
            if np.any(rotations[:, j] != rotations[0, j]):  # a joint held still keeps its node's rotation: no channel
                animation.add(j + 1, "rotation", keys, buf.array(np.concatenate([rotations[:, j], rotations[-1:, j]]), "VEC4"))
        animation.add(1, "translation", keys, buf.array(np.concatenate([root, root[-1:]]), "VEC3"))
    mesh = {"name": name, "primitives": [{"attributes": attributes, "indices": indices, "mode": 4, "material": 0}]}
    gltf = gltf_document(buf, animation, nodes, [mesh], name, fps, extras)
    gltf["scenes"][0]["nodes"] = [0, 1]
    gltf["skins"] = [skin]
    return write_glb_file(Path(path), gltf, buf.blobs)


def _quaternions(rotations: np.ndarray) -> np.ndarray:
    """Unit quaternions (xyzw, glTF's order) of rotation matrices ``(..., 3, 3)``, normalised in float32."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(rotations.reshape(-1, 3, 3)).as_quat().reshape(*rotations.shape[:-2], 4).astype(np.float32)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)

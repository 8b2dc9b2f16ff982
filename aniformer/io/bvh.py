"""Biovision hierarchy (BVH) of a rig's motion (``jobs/animate.py --rig``): the skeleton and one MOTION row
per frame, for tools that retarget motion rather than meshes (Blender's importer, MotionBuilder).

BVH has no bind matrices: a joint's rest orientation is its parent's, and OFFSETs are in world axes.
So every joint's frame here is world-aligned at the bind pose (the target's own pose): OFFSETs are the
differences of bind joint positions, and a joint's rotation on frame k is its world turn since bind
relative to its parent's. The rest pose of the file is thus the target's pose. Axes: y up (BVH's
usual convention and Blender's importer default), as ``aniformer.io.glb`` writes them; unit: the
target's (``metres_per_unit``). Rotation channels are ZXY Euler angles in degrees (intrinsic:
R = Rz Rx Ry), as every CHANNELS line states.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from aniformer.io.files import atomic_path
from aniformer.io.glb import GLTF_AXES

EULER_ORDER = "ZXY"
END_SITE = 0.5  # a leaf joint's End Site: this fraction of its own offset further on


def depth_first(parents: np.ndarray) -> list[int]:
    """Joint indices in the order a BVH HIERARCHY lists them (each joint, then its subtrees)."""
    children = {j: [c for c in range(len(parents)) if parents[c] == j] for j in range(len(parents))}
    order, stack = [], [int(np.flatnonzero(parents < 0)[0])]
    while stack:
        joint = stack.pop()
        order.append(joint)
        stack.extend(reversed(children[joint]))
    return order


def write_bvh(path: str | os.PathLike, rig, motion, fps: float, metres_per_unit: float = 1.0) -> Path:
    """Write ``rig`` (``aniformer.rig.Rig``) and ``motion`` (``aniformer.rig_motion.RigMotion``) as a BVH file,
    atomically (see the module doc for the axes, unit and Euler order)."""
    bind_rotation, bind_position = rig.bind[:, :3, :3], rig.bind[:, :3, 3]
    world = np.asarray(motion.world, np.float64)
    turn = GLTF_AXES @ world[..., :3, :3] @ np.swapaxes(bind_rotation, -1, -2) @ GLTF_AXES.T  # (N, J, 3, 3)
    parent_turn = np.where(rig.parents[None, :, None, None] >= 0, turn[:, np.maximum(rig.parents, 0)], np.eye(3))
    local = np.swapaxes(parent_turn, -1, -2) @ turn
    offsets = (bind_position - np.where(rig.parents[:, None] >= 0, bind_position[np.maximum(rig.parents, 0)],
                                        bind_position)) @ GLTF_AXES.T / metres_per_unit
    order = depth_first(rig.parents)
    angles = Rotation.from_matrix(local[:, order].reshape(-1, 3, 3)).as_euler(EULER_ORDER, degrees=True)
    root = world[:, order[0], :3, 3] @ GLTF_AXES.T / metres_per_unit
    rows = np.concatenate([root, angles.reshape(len(world), -1)], 1)
    lines = ["HIERARCHY"]
    _hierarchy(lines, rig, offsets, order[0], 0)
    lines += ["MOTION", f"Frames: {len(world)}", f"Frame Time: {1.0 / fps:.8f}"]
    body = "\n".join(lines) + "\n" + "".join(" ".join(f"{v:.6f}" for v in row) + "\n" for row in rows)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(body)
    return Path(path)


def _hierarchy(lines: list[str], rig, offsets: np.ndarray, joint: int, depth: int) -> None:
    pad = "  " * depth
    root = rig.parents[joint] < 0
    channels = ("6 Xposition Yposition Zposition" if root else "3") + " " + " ".join(
        f"{axis}rotation" for axis in EULER_ORDER)
    offset = np.zeros(3) if root else offsets[joint]
    lines += [f"{pad}{'ROOT' if root else 'JOINT'} {rig.names[joint]}", f"{pad}{{",
              f"{pad}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}", f"{pad}  CHANNELS {channels}"]
    children = [c for c in range(len(rig.parents)) if rig.parents[c] == joint]
    for child in children:
        _hierarchy(lines, rig, offsets, child, depth + 1)
    if not children:
        tip = END_SITE * offset
        lines += [f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {tip[0]:.6f} {tip[1]:.6f} {tip[2]:.6f}", f"{pad}  }}"]
    lines.append(f"{pad}}}")

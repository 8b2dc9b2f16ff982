"""Make a skinned, animated GLB in Blender, as a user's rigged character with a clip comes, and keep Blender's
own evaluation of every frame beside it: what ``aniformer.io.gltf_clip`` must read out of the file.

    blender -b --factory-startup --python-exit-code 1 --python bench/blender_skinned_clip.py -- clip.glb clip.npy

Runs inside Blender (Debian's 3.4.1, headless) with Blender's Python and numpy. The scene: a 1 m tube of
rings along z, skinned to a chain of three bones with weights blended across each joint; the armature object
turned, scaled and moving (root motion through the hierarchy), the upper bones bending with Bezier keys, at
24 fps over frames 1 … 25. Exported with Blender's glTF exporter (y up, its default sampling of the
animation), and ``clip.npy`` holds the mesh evaluated in Blender's world space (z up) at each frame ``(25, V, 3)``.
"""

from __future__ import annotations

import math
import sys

import bpy
import numpy as np

RINGS, SIDES, FRAMES = 21, 12, 25


def tube() -> bpy.types.Object:
    heights = np.linspace(0.0, 1.0, RINGS)
    angles = np.linspace(0.0, 2 * math.pi, SIDES, endpoint=False)
    vertices = [(0.1 * math.cos(a), 0.1 * math.sin(a), z) for z in heights for a in angles]
    faces = [(r * SIDES + s, r * SIDES + (s + 1) % SIDES, (r + 1) * SIDES + (s + 1) % SIDES, (r + 1) * SIDES + s)
             for r in range(RINGS - 1) for s in range(SIDES)]
    mesh = bpy.data.meshes.new("tube")
    mesh.from_pydata(vertices, [], faces)
    obj = bpy.data.objects.new("tube", mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def armature() -> bpy.types.Object:
    data = bpy.data.armatures.new("rig")
    obj = bpy.data.objects.new("rig", data)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    parent = None
    for k, (head, tail) in enumerate(((0.0, 1 / 3), (1 / 3, 2 / 3), (2 / 3, 1.0))):
        bone = data.edit_bones.new(f"bone{k}")
        bone.head, bone.tail, bone.parent = (0.0, 0.0, head), (0.0, 0.0, tail), parent
        bone.use_connect = parent is not None
        parent = bone
    bpy.ops.object.mode_set(mode="OBJECT")
    return obj


def skin(body: bpy.types.Object, rig: bpy.types.Object) -> None:
    """Weights blended linearly over 0.1 m around each joint; the body parented to the armature."""
    groups = [body.vertex_groups.new(name=f"bone{k}") for k in range(3)]
    for vertex in body.data.vertices:
        z = vertex.co.z
        for k, group in enumerate(groups):
            lower = 1.0 if k == 0 else np.clip((z - (k / 3 - 0.05)) / 0.1, 0.0, 1.0)
            upper = 1.0 if k == 2 else np.clip(((k + 1) / 3 + 0.05 - z) / 0.1, 0.0, 1.0)
            weight = float(min(lower, upper))
            if weight > 0:
                group.add([vertex.index], weight, "REPLACE")
    body.parent = rig
    body.modifiers.new("rig", "ARMATURE").object = rig


def animate(rig: bpy.types.Object) -> None:
    scene = bpy.context.scene
    rig.rotation_mode, rig.scale = "XYZ", (1.2, 1.2, 1.2)
    for frame, x, turn, bend in ((1, 0.0, 0.0, 0.0), (13, 0.4, 0.6, 0.9), (25, 1.0, 1.2, -0.5)):
        scene.frame_set(frame)
        rig.location, rig.rotation_euler = (x, 0.0, 0.1 * x), (0.0, 0.0, turn)
        rig.keyframe_insert("location")
        rig.keyframe_insert("rotation_euler")
        for name, axis in (("bone1", (1.0, 0.0, 0.0)), ("bone2", (0.0, 1.0, 0.0))):
            pose = rig.pose.bones[name]
            pose.rotation_mode = "AXIS_ANGLE"
            pose.rotation_axis_angle = (bend, *axis)
            pose.keyframe_insert("rotation_axis_angle")


def evaluated(body: bpy.types.Object) -> np.ndarray:
    scene, frames = bpy.context.scene, []
    for frame in range(1, FRAMES + 1):
        scene.frame_set(frame)
        moved = body.evaluated_get(bpy.context.evaluated_depsgraph_get())
        mesh = moved.to_mesh()
        co = np.empty(3 * len(mesh.vertices))
        mesh.vertices.foreach_get("co", co)
        world = np.array(moved.matrix_world)
        frames.append(co.reshape(-1, 3) @ world[:3, :3].T + world[:3, 3])
        moved.to_mesh_clear()
    return np.stack(frames)


def main() -> None:
    glb, npy = sys.argv[sys.argv.index("--") + 1:][:2]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.frame_start, scene.frame_end = 24, 1, FRAMES
    body, rig = tube(), armature()
    skin(body, rig)
    animate(rig)
    bpy.ops.export_scene.gltf(filepath=glb, export_format="GLB", export_animations=True, export_skins=True)
    np.save(npy, evaluated(body))


main()

"""Make a skinned, animated GLB in Blender, as a user's rigged character with a clip comes, and keep Blender's
own evaluation of every frame beside it: what ``aniformer.io.gltf_clip`` must read out of the file.

    blender -b --factory-startup --python-exit-code 1 --python bench/blender_skinned_clip.py -- clip.glb clip.npy

Runs inside Blender (Debian's 3.4.1, headless) with Blender's Python and numpy. The scene: a 1 m tube of
rings along z, skinned to a chain of three bones with weights blended across each joint, with a shape key
(its middle bulging) keyed on and off; a box parented to the top bone (a hat, moved rigidly by it); the
armature object turned, scaled and moving (root motion through the hierarchy), the upper bones bending with
Bezier keys, at 24 fps over frames 1 … 25. Exported with Blender's glTF exporter (y up, its default sampling
of the animation: morph targets and their weights, the hat a child node of the bone's), and ``clip.npy``
holds the tube's and the hat's vertices evaluated in Blender's world space (z up) at each frame ``(25, V, 3)``.
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


def bulge(body: bpy.types.Object) -> None:
    """A shape key pushing the middle rings out by half their radius, keyed 0, 1, 0."""
    body.shape_key_add(name="basis")
    key = body.shape_key_add(name="bulge")
    for vertex, point in zip(body.data.vertices, key.data):
        if 0.3 < vertex.co.z < 0.7:
            point.co = (1.5 * vertex.co.x, 1.5 * vertex.co.y, vertex.co.z)
    for frame, value in ((1, 0.0), (13, 1.0), (25, 0.0)):
        key.value = value
        key.keyframe_insert("value", frame=frame)


def hat(rig: bpy.types.Object) -> bpy.types.Object:
    """A 10 cm box on the top bone, moved rigidly by it."""
    mesh = bpy.data.meshes.new("hat")
    corners = [(x, y, z) for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (0.0, 0.1)]
    mesh.from_pydata(corners, [], [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)])
    obj = bpy.data.objects.new("hat", mesh)
    bpy.context.scene.collection.objects.link(obj)
    obj.parent, obj.parent_type, obj.parent_bone = rig, "BONE", "bone2"
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


def evaluated(objects: list[bpy.types.Object]) -> np.ndarray:
    scene, frames = bpy.context.scene, []
    for frame in range(1, FRAMES + 1):
        scene.frame_set(frame)
        parts = []
        for obj in objects:
            moved = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
            mesh = moved.to_mesh()
            co = np.empty(3 * len(mesh.vertices))
            mesh.vertices.foreach_get("co", co)
            world = np.array(moved.matrix_world)
            parts.append(co.reshape(-1, 3) @ world[:3, :3].T + world[:3, 3])
            moved.to_mesh_clear()
        frames.append(np.concatenate(parts))
    return np.stack(frames)


def main() -> None:
    glb, npy = sys.argv[sys.argv.index("--") + 1:][:2]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.frame_start, scene.frame_end = 24, 1, FRAMES
    body, rig = tube(), armature()
    skin(body, rig)
    bulge(body)
    top = hat(rig)
    animate(rig)
    # the armature's and the shape key's actions as one glTF animation, the clip a user made
    bpy.ops.export_scene.gltf(filepath=glb, export_format="GLB", export_animations=True, export_skins=True,
                              export_morph=True, export_nla_strips=False,
                              export_nla_strips_merged_animation_name="bend")
    np.save(npy, evaluated([body, top]))


main()

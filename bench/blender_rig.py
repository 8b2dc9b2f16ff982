"""Import animate --rig's rigged.glb and motion.bvh into Blender, check what Blender makes of them, render the
armature over the skinned mesh.

    blender -b --factory-startup --python-exit-code 1 --python bench/blender_rig.py -- anim/jump \\
        --png docs/animate_rig_blender.png

Runs inside Blender (Debian's 3.4.1, headless) with only Blender's Python and numpy, as
bench/blender_import.py (whose helpers it uses). In a fresh scene at the clip's frame rate:

1. imports ``OUT/rigged.glb``: one armature whose bone count is animation.json's ``rig.joints``, one
   mesh skinned by it (an Armature modifier) and no shape keys; the armature's action spans frames
   0 … N; the mesh evaluated in world space at every frame is within ``rig.residual_m`` + 1 mm RMS
   of ``OUT/frames`` (OBJs in metres, in the target's axes: a y-up target's turned z-up as Blender's
   glTF importer turns glTF's);
2. imports ``OUT/motion.bvh`` into a second fresh scene: an armature of as many bones, its action
   spanning the clip's frames;
3. with ``--png``: the glTF import at ``--frame`` (default N // 2), the mesh half transparent and every
   bone a red stick from head to tail, rendered with Cycles.

Prints one ``blender_rig: {...}`` JSON line (``--json`` also writes it) and exits 1 after ``FAIL: …`` lines.
"""

from __future__ import annotations

import argparse
import builtins
import contextlib
import json
import sys
from pathlib import Path

import bpy
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from blender_import import finish, obj_vertices, render, world_vertices  # noqa: E402


def parse_args() -> argparse.Namespace:
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    p = argparse.ArgumentParser(prog="blender -b --python bench/blender_rig.py --", description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path, help="a jobs/animate.py --rig output folder")
    p.add_argument("--frame", type=int, help="frame to render (default: N // 2)")
    p.add_argument("--png", type=Path)
    p.add_argument("--resolution", type=int, nargs=2, default=(360, 400), metavar=("W", "H"))
    p.add_argument("--samples", type=int, default=24)
    p.add_argument("--json", type=Path)
    return p.parse_args(argv)


def fresh_scene(fps: float) -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = round(fps), 1.0  # importers turn seconds into frames at this rate
    return scene


def armatures(scene) -> list:
    return [o for o in scene.objects if o.type == "ARMATURE"]


def action_span(obj) -> tuple[float, float] | None:
    action = obj.animation_data.action if obj.animation_data else None
    return tuple(round(x, 3) for x in action.frame_range) if action else None


def bone_sticks(armature) -> None:
    """A red stick mesh from each posed bone's head to its tail, in world space (bones do not render)."""
    matrix = np.array(armature.matrix_world)
    vertices, faces = [], []
    for bone in armature.pose.bones:
        head, tail = (matrix[:3, :3] @ np.array(p) + matrix[:3, 3] for p in (bone.head, bone.tail))
        axis = tail - head
        side = np.cross(axis, [0, 0, 1] if abs(axis[2]) < 0.9 * np.linalg.norm(axis) else [1, 0, 0])
        side = 0.006 * side / (np.linalg.norm(side) + 1e-12)
        up = np.cross(axis, side)
        up = 0.006 * up / (np.linalg.norm(up) + 1e-12)
        base = len(vertices)
        vertices += [tuple(p) for p in (head + side, head + up, head - side, head - up,
                                        tail + side, tail + up, tail - side, tail - up)]
        faces += [(base + i, base + (i + 1) % 4, base + 4 + (i + 1) % 4, base + 4 + i) for i in range(4)]
    mesh = bpy.data.meshes.new("bones")
    mesh.from_pydata(vertices, [], faces)
    sticks = bpy.data.objects.new("bones", mesh)
    material = bpy.data.materials.new("bones")
    material.use_nodes = True
    material.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.8, 0.05, 0.05, 1)
    mesh.materials.append(material)
    bpy.context.scene.collection.objects.link(sticks)


@contextlib.contextmanager
def universal_newlines_mode():
    """Blender 3.4's BVH importer opens files with mode "rU", which Python 3.11 (Debian's Blender runs on
    it) refuses; "r" is what "rU" meant."""
    original = builtins.open

    def patched(file, mode="r", *args, **kwargs):
        return original(file, mode.replace("U", ""), *args, **kwargs)

    builtins.open = patched
    try:
        yield
    finally:
        builtins.open = original


def main() -> int:
    args = parse_args()
    summary = json.loads((args.out / "animation.json").read_text())
    frames, fps, rig = summary["frames"], summary["fps"], summary["rig"]
    failures = []
    report = {"blender": bpy.app.version_string, "frames": frames, "fps": fps, "joints": rig["joints"]}

    scene = fresh_scene(fps)
    bpy.ops.import_scene.gltf(filepath=str(args.out / "rigged.glb"), import_shading="SMOOTH")
    scene.frame_start, scene.frame_end = 0, frames - 1
    meshes = [o for o in scene.objects if o.type == "MESH"]
    skeleton = armatures(scene)
    report["gltf"] = {"armatures": len(skeleton), "bones": [len(a.data.bones) for a in skeleton],
                      "action": action_span(skeleton[0]) if skeleton else None,
                      "armature_modifiers": [m.type for o in meshes for m in o.modifiers],
                      "shape_keys": sum(o.data.shape_keys is not None for o in meshes)}
    if len(skeleton) != 1 or len(skeleton[0].data.bones) != rig["joints"]:
        failures.append(f"glTF: {report['gltf']['bones']} armature bones, not one armature of {rig['joints']}")
    if report["gltf"]["armature_modifiers"] != ["ARMATURE"] or report["gltf"]["shape_keys"]:
        failures.append(f"glTF: the mesh is not skinned by one armature alone: {report['gltf']}")
    if frames > 1 and report["gltf"]["action"] != (0.0, float(frames)):
        failures.append(f"glTF: the armature's action spans {report['gltf']['action']}, not 0 … {frames}")
    errors = []
    for k in range(frames):
        mine, _ = world_vertices(k)
        reference = obj_vertices(args.out / "frames" / f"frame_{k:0{max(4, len(str(frames - 1)))}d}.obj")
        if summary["up"]["target"]["axis"] == "y":  # a y-up target's own axes, turned z-up as the importer turns glTF's
            reference = reference[:, [0, 2, 1]] * [1, -1, 1]
        if mine.shape != reference.shape:
            failures.append(f"frame {k}: {len(mine)} vertices in Blender, {len(reference)} in the OBJ")
            break
        errors.append(np.square(mine - reference).sum(1).mean())
    rms = float(np.sqrt(np.mean(errors))) if errors else float("inf")
    report["rms_from_obj_frames_m"] = round(rms, 5)
    if rms > rig["residual_m"] + 1e-3:
        failures.append(f"the skinned mesh is {rms:.4f} m RMS from the OBJ frames; the job reported {rig['residual_m']}")
    if args.png is not None:
        frame = args.frame if args.frame is not None else frames // 2
        body, _ = world_vertices(frame)
        for obj in meshes:
            material = obj.active_material
            material.use_nodes = True
            material.node_tree.nodes["Principled BSDF"].inputs["Alpha"].default_value = 0.35
            material.blend_method = "BLEND"
        bone_sticks(skeleton[0])
        report["render_seconds"] = round(render(args.png, frame, body, args), 2)

    scene = fresh_scene(fps)
    with universal_newlines_mode():
        bpy.ops.import_anim.bvh(filepath=str(args.out / "motion.bvh"), update_scene_fps=False,
                                update_scene_duration=True)
    skeleton = armatures(scene)
    report["bvh"] = {"armatures": len(skeleton), "bones": [len(a.data.bones) for a in skeleton],
                     "action": action_span(skeleton[0]) if skeleton else None}
    if len(skeleton) != 1 or len(skeleton[0].data.bones) != rig["joints"]:
        failures.append(f"BVH: {report['bvh']['bones']} armature bones, not one armature of {rig['joints']}")
    span = report["bvh"]["action"]
    if span is None or round(span[1] - span[0]) != frames - 1:
        failures.append(f"BVH: the action spans {span}, not {frames} frames")

    return finish("blender_rig", report, failures, args.json)


if __name__ == "__main__":
    sys.exit(main())

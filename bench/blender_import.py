"""Import an animation.glb of jobs/animate.py into Blender, check what Blender makes of it, render a frame.

    blender -b --factory-startup --python-exit-code 1 --python bench/blender_import.py -- \\
        anim/jump/animation.glb --objs anim/jump/frames --airborne 0.3 --png docs/animate_blender_jump.png

Runs inside Blender (tested with Debian's 3.4.1, headless): only Blender's Python, its numpy and
the standard library, nothing of this project. What it does, as a user would:

1. reads the clip's frame rate from the GLB (``scenes[0].extras.fps``; ``--fps`` overrides) and sets
   the scene's frame rate *before* importing: glTF keys are seconds, and Blender's importer turns
   them into frames at the scene's rate (its default is 24, whatever the file says);
2. imports with ``bpy.ops.import_scene.gltf`` (``import_shading="SMOOTH"``: the default "NORMALS"
   mode uses ``np.bool``, which Debian's numpy 1.24 no longer has; our GLBs have no normals, so
   both modes give the same flat shading) and sets the scene's range to the clip's frames 0 … N−1;
3. evaluates the visible mesh (shape keys, chunk visibility, root motion) in world space at frame 0
   and at ``--frame`` (default N // 2) and checks:

   - the importer's actions (together) span frames 0 … N at the scene's rate: the clip lasts N / fps;
   - exactly one chunk is visible at each frame;
   - the body stands up: its z extent (Blender is z up) at frame 0 is the body height, which is
     ``--height`` or the z extent of ``--objs``'s frame_0000.obj (the job's z-up OBJ frames);
   - with ``--objs``: every vertex is where the OBJ frame has it (within 0.1 mm);
   - the mesh has moved between frame 0 and ``--frame`` (by more than 1 cm);
   - with ``--airborne R``: it stands on the floor (lowest z = 0) at frame 0 and its lowest point
     is at least R metres up at ``--frame``;

4. with ``--png``: renders ``--frame`` with Cycles on the CPU (a floor, a sun, a low camera so the
   gap under the feet shows) to a PNG.

Prints one ``blender_import: {...}`` JSON line (``--json`` also writes it to a file) and exits with
status 1 after ``FAIL: …`` lines when a check fails.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys
import time
from pathlib import Path

import bpy
import numpy as np

GLB_MAGIC = 0x46546C67


def parse_args() -> argparse.Namespace:
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    p = argparse.ArgumentParser(prog="blender -b --python bench/blender_import.py --",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("glb", type=Path)
    p.add_argument("--fps", type=float, help="frame rate to import at (default: the GLB's scenes[0].extras.fps)")
    p.add_argument("--frame", type=int, help="frame to check and render (default: N // 2)")
    p.add_argument("--height", type=float, help="the body's height in metres (z extent at frame 0)")
    p.add_argument("--objs", type=Path, help="the job's frames/ (z-up OBJs in metres) to compare every vertex with")
    p.add_argument("--airborne", type=float, help="require the lowest point at --frame this many metres up")
    p.add_argument("--png", type=Path, help="render --frame to this PNG")
    p.add_argument("--resolution", type=int, nargs=2, default=(360, 400), metavar=("W", "H"))
    p.add_argument("--samples", type=int, default=24, help="Cycles samples (default: 24)")
    p.add_argument("--json", type=Path, help="also write the report here")
    return p.parse_args(argv)


def glb_json(path: Path) -> dict:
    """The JSON chunk of a GLB (what the file says about itself, before Blender reads it)."""
    with open(path, "rb") as f:
        magic, _, _ = struct.unpack("<III", f.read(12))
        length, _ = struct.unpack("<II", f.read(8))
        if magic != GLB_MAGIC:
            raise SystemExit(f"FAIL: {path} is not a GLB")
        return json.loads(f.read(length))


def obj_vertices(path: Path) -> np.ndarray:
    """The ``v`` lines of an OBJ, in file order."""
    rows = [line.split()[1:4] for line in path.read_text().splitlines() if line.startswith("v ")]
    return np.array(rows, dtype=np.float64)


def world_vertices(frame: int) -> tuple[np.ndarray, int]:
    """World-space vertices of the visible mesh objects at ``frame`` (hidden chunks have scale 0)."""
    scene = bpy.context.scene
    scene.frame_set(frame)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    parts = []
    for obj in scene.objects:
        if obj.type != "MESH":
            continue
        evaluated = obj.evaluated_get(depsgraph)
        matrix = np.array(evaluated.matrix_world)
        if abs(np.linalg.det(matrix[:3, :3])) < 1e-12:  # a chunk switched off by its scale channel
            continue
        mesh = evaluated.to_mesh()
        co = np.empty(3 * len(mesh.vertices))
        mesh.vertices.foreach_get("co", co)
        evaluated.to_mesh_clear()
        parts.append(co.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3])
    return (np.concatenate(parts) if parts else np.zeros((0, 3))), len(parts)


def stats(v: np.ndarray) -> dict:
    low, high = v.min(0), v.max(0)
    return {"z_extent": round(float(high[2] - low[2]), 4), "lowest_z": round(float(low[2]), 4),
            "centre": [round(float(c), 4) for c in (low + high) / 2]}


def render(png: Path, frame: int, vertices: np.ndarray, args: argparse.Namespace) -> float:
    """Cycles on the CPU: a checker floor at z = 0, a sun, a camera at knee height looking at the body."""
    scene = bpy.context.scene
    scene.frame_set(frame)
    low, high = vertices.min(0), vertices.max(0)
    centre, size = (low + high) / 2, high - low
    bpy.ops.mesh.primitive_plane_add(size=40, location=(float(centre[0]), float(centre[1]), 0))
    floor = bpy.context.active_object
    material = bpy.data.materials.new("floor")
    material.use_nodes = True
    nodes = material.node_tree.nodes
    checker = nodes.new("ShaderNodeTexChecker")
    checker.inputs["Scale"].default_value = 40.0  # 1 m squares on the 40 m plane
    checker.inputs["Color1"].default_value = (0.25, 0.25, 0.25, 1)
    checker.inputs["Color2"].default_value = (0.4, 0.4, 0.4, 1)
    material.node_tree.links.new(checker.outputs["Color"], nodes["Principled BSDF"].inputs["Base Color"])
    floor.data.materials.append(material)
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(20), math.radians(-15), 0))
    bpy.context.active_object.data.energy = 2.5
    scene.world = scene.world or bpy.data.worlds.new("world")
    scene.world.use_nodes = True
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.3, 0.33, 0.38, 1)
    scene.view_settings.view_transform = "Standard"
    # A 50 mm lens on Blender's 36 mm sensor: tan(half angle) = 18 / 50 across the image's larger side.
    width, height = args.resolution
    tan_v, tan_h = 18 / 50 * min(1.0, height / width), 18 / 50 * min(1.0, width / height)
    distance = 1.2 * max(0.5 * float(high[2]) / tan_v, 0.5 * float(size[0]) / tan_h)
    eye = (float(centre[0]), float(centre[1]) - distance, 0.35)  # low: the gap under the feet shows
    tilt = math.atan2(0.5 * float(high[2]) - eye[2], distance)
    bpy.ops.object.camera_add(location=eye, rotation=(math.pi / 2 + tilt, 0, 0))
    scene.camera = bpy.context.active_object
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = args.samples
    scene.cycles.use_denoising = False  # Debian's Blender is built without OpenImageDenoise
    scene.render.resolution_x, scene.render.resolution_y = args.resolution
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"
    scene.render.image_settings.compression = 100
    scene.render.filepath = str(png.resolve())
    start = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    return time.perf_counter() - start


def main() -> int:
    args = parse_args()
    gltf = glb_json(args.glb)
    extras = gltf["scenes"][gltf.get("scene", 0)].get("extras", {})
    frames = int(extras.get("frames", 1))
    fps = args.fps or float(extras.get("fps", 0)) or None
    if fps is None:
        raise SystemExit("FAIL: the GLB's scene has no extras.fps: pass --fps")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    report = {"blender": bpy.app.version_string, "glb": str(args.glb), "frames": frames,
              "fps_in_file": extras.get("fps"), "blender_default_fps": scene.render.fps}
    # The importer converts key times with scene.render.fps (an integer; fps_base is not used).
    scene.render.fps, scene.render.fps_base = round(fps), 1.0
    if scene.render.fps != fps:
        report["note"] = f"{fps} fps is not an integer: keys land at t * {scene.render.fps}"
    bpy.ops.import_scene.gltf(filepath=str(args.glb), import_shading="SMOOTH")
    active = [o.data.shape_keys if o.type == "MESH" else o for o in scene.objects]
    actions = [a.animation_data.action for a in active if a and a.animation_data and a.animation_data.action]
    ranges = sorted({tuple(round(x, 3) for x in a.frame_range) for a in actions})
    scene.frame_start, scene.frame_end = 0, max(frames - 1, 0)
    report.update(fps=scene.render.fps, action_frame_ranges=ranges, frame_range=[scene.frame_start, scene.frame_end],
                  seconds=round((scene.frame_end - scene.frame_start + 1) / scene.render.fps, 4),
                  scene_custom_properties={k: scene[k] for k in scene.keys() if isinstance(scene[k], int | float | str)},
                  objects=sorted(f"{o.name} ({o.type})" for o in scene.objects))
    failures = []
    span = (min(r[0] for r in ranges), max(r[1] for r in ranges)) if ranges else None
    if frames > 1 and span != (0.0, float(frames)):  # keys k / fps for k = 0 … N (the end key)
        failures.append(f"the imported actions span frames {span}, not 0 … {frames} at {scene.render.fps} fps")

    frame = args.frame if args.frame is not None else frames // 2
    first, shown_first = world_vertices(0)
    now, shown_now = world_vertices(frame)
    report.update(frame=frame, frame_0=stats(first), **{f"frame_{frame}": stats(now)},
                  visible_chunks=[shown_first, shown_now])
    if shown_first != 1 or shown_now != 1:
        failures.append(f"{shown_first} and {shown_now} chunks visible at frames 0 and {frame}, not 1")
    height = args.height
    if args.objs is not None:
        reference = {k: obj_vertices(args.objs / f"frame_{k:04d}.obj") for k in (0, frame)}
        height = height or float(np.ptp(reference[0][:, 2]))
        for k, mine in ((0, first), (frame, now)):
            if mine.shape != reference[k].shape:  # Blender's importer drops vertices no triangle uses
                failures.append(f"frame {k}: {len(mine)} vertices in Blender, {len(reference[k])} in the OBJ")
                continue
            deviation = float(np.abs(mine - reference[k]).max())
            report[f"max_deviation_from_obj_frame_{k}_m"] = deviation
            if deviation > 1e-4:
                failures.append(f"frame {k}: a vertex is {deviation:.4f} m from where frame_{k:04d}.obj has it")
    if height is not None:
        report["height"] = round(height, 4)
        if abs(report["frame_0"]["z_extent"] - height) > max(0.01 * height, 1e-3):
            failures.append(f"z extent {report['frame_0']['z_extent']} m at frame 0 is not the body height "
                            f"{height:.4f} m: the body does not stand up in Blender (z up)")
    moved = float(np.abs(now - first).max()) if now.shape == first.shape else float("inf")
    report["max_move_m"] = round(moved, 4)
    if moved < 0.01:
        failures.append(f"nothing moved between frames 0 and {frame} (at most {moved:.4f} m)")
    if args.airborne is not None:
        if abs(report["frame_0"]["lowest_z"]) > 0.01:
            failures.append(f"the lowest point at frame 0 is at z = {report['frame_0']['lowest_z']} m, not on the floor")
        if report[f"frame_{frame}"]["lowest_z"] < args.airborne:
            failures.append(f"the lowest point at frame {frame} is at z = {report[f'frame_{frame}']['lowest_z']} m, "
                            f"below {args.airborne} m: not in the air")
    if args.png is not None:
        report["render_seconds"] = round(render(args.png, frame, now, args), 2)
        report["png"] = str(args.png)
    return finish("blender_import", report, failures, args.json)


def finish(name: str, report: dict, failures: list[str], json_path: Path | None) -> int:
    """Print the report as one ``name: {...}`` JSON line (and write it to ``json_path``), then each
    ``FAIL: …``; the exit status: 1 after a failure."""
    report["failures"] = failures
    line = json.dumps(report)
    print(f"{name}: {line}")
    if json_path is not None:
        json_path.write_text(line + "\n")
    for failure in failures:
        print(f"FAIL: {failure}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

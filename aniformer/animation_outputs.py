"""What an animation run writes (no Ray, no MLflow): the inferred frames (`aniformer.animation_run.infer`) placed
in the world, then frames/*.obj, animation.glb, preview.gif, animation.json and with ``--rig`` rigged.glb and
motion.bvh, staged into the output directory (`write_animation`, for jobs/animate.py and pipeline/retarget.py).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import json
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from aniformer.animation_run import AnimateOptions, Inference, anny_topology, timed
from aniformer.cli.outputs import staged_output_dir
from aniformer.io.mesh import UNITS

# vertex-frames from which the OBJs get a writer process: below, its start (~0.3 s of a core) outweighs the overlap
OBJ_PROCESS_VERTEX_FRAMES = 1_000_000


def rig_inputs(options: AnimateOptions, state: dict, target, target_faces, registrations: dict):
    """(the target's vertices on an Anny topology, that topology, where each target vertex lies on it or None)
    for ``aniformer.rig.build_rig``: the registration's, else the target itself when it is an Anny mesh, else
    a registration made here (a model of absolute output registers nothing)."""
    from aniformer.correspondence import register_mesh

    if "target" in registrations:
        fit = registrations["target"]
        return fit.template, fit.topology, fit.mesh_on_template
    topology = anny_topology(target, target_faces)
    if topology is not None:
        return target, topology, None
    fit = register_mesh(target, target_faces, options.template or (state["config"].get("data") or {}).get("topology"))
    return fit.template, fit.topology, fit.mesh_on_template


def write_rig(tmp: Path, options: AnimateOptions, summary: dict, target, target_faces, world, rig_source) -> None:
    """rigged.glb and motion.bvh of the animated ``world`` frames; the rig's size and fit into ``summary``."""
    from aniformer.io.bvh import write_bvh
    from aniformer.io.rigged_glb import write_rigged_glb
    from aniformer.rig import build_rig
    from aniformer.rig_motion import fit_rig

    rig, motion = fit_rig(build_rig(target, *rig_source, bone_names=options.bone_names), target, world)
    write_rigged_glb(tmp / "rigged.glb", target, target_faces, rig, motion, fps=summary["fps"], name=summary["name"],
                     extras={"checkpoint": str(options.checkpoint), "driving": str(options.driving)})
    write_bvh(tmp / "motion.bvh", rig, motion, summary["fps"], UNITS[summary["unit"]])
    summary["rig"] = {"joints": len(rig.names), "residual_m": round(motion.residual, 6)}


def objs_in_a_process(frames: int, vertices: int) -> bool:
    """Whether a clip's OBJs are worth a writer process: big enough, and a second CPU for it."""
    return frames * vertices >= OBJ_PROCESS_VERTEX_FRAMES and len(os.sched_getaffinity(0)) > 1


@contextlib.contextmanager
def objs_written_beside(folder: Path, frames, faces, in_process: bool, seconds: dict, bar) -> Iterator[None]:
    """frame_NNNN.obj of ``frames`` in ``folder``, written while the block writes the other outputs: in a process of
    its own when ``in_process`` (their text is built under the GIL, so a thread would not overlap), else here first.
    ``seconds["write OBJ"]`` is what the OBJs cost this process: the writing, or saving the frames for the writer
    and waiting for it after the block. A failure in either ends both."""
    import multiprocessing

    import numpy as np

    from aniformer.io.mesh import write_obj_frames

    folder.mkdir()
    if not in_process:
        with timed(seconds, "write OBJ"):
            write_obj_frames(folder, frames, faces, progress=bar.update)
        yield
        return
    handoff = folder.parent / ".frames.npy"  # in the staging directory: the writer reads it a frame at a time
    with timed(seconds, "write OBJ"):
        np.save(handoff, np.asarray(frames))
    writer = multiprocessing.get_context("spawn").Pool(1)  # spawn: this process holds torch's threads
    try:
        written = writer.apply_async(write_obj_frames, (folder, handoff, np.asarray(faces)))
        yield
        with timed(seconds, "write OBJ"):
            while not written.ready():
                written.wait(0.2)
                bar.update(sum(1 for name in os.listdir(folder) if name.startswith("frame_")) - bar.n)
            written.get()  # the writer's exception, if it raised
        bar.update(bar.total - bar.n)
    finally:
        writer.terminate()
        writer.join()
        handoff.unlink(missing_ok=True)


def write_outputs(out: Path, options: AnimateOptions, summary: dict, driving, driving_faces, local, translation,
                  target, target_faces, rig_source, objs_process: bool = False) -> None:
    """frames/*.obj, animation.glb, preview.gif, animation.json and with ``--rig`` rigged.glb and motion.bvh (of
    ``rig_source``: ``rig_inputs``), staged: `out` appears complete or not at all. Each one's time goes into
    ``summary["seconds"]``. ``objs_process``: the OBJs may be written by a process of their own
    (`objs_in_a_process`), beside the rest."""
    from tqdm import tqdm

    from aniformer.geometry import center_bbox, from_z_up
    from aniformer.io.glb import write_glb

    seconds = summary["seconds"]
    world = local if translation is None else local + translation[:, None]
    fps, name = summary["fps"], summary["name"]
    in_process = objs_process and objs_in_a_process(len(local), len(target))
    in_target_axes = from_z_up(world, summary["up"]["target"]["axis"])
    if UNITS[summary["unit"]] != 1:  # metres are written as they are: no copy of the clip
        in_target_axes = in_target_axes / UNITS[summary["unit"]]
    with staged_output_dir(out, options.overwrite) as tmp:
        def glb() -> None:
            with timed(seconds, "write GLB"):
                write_glb(tmp / "animation.glb", local, target_faces, fps=fps, name=name, translation=translation,
                          frames_per_mesh=options.frames_per_mesh,
                          extras={"checkpoint": str(options.checkpoint), "driving": str(options.driving)})

        with tqdm(total=len(local), unit="obj", desc="write OBJ", disable=options.no_progress,
                  file=sys.stderr) as obj_bar, \
                objs_written_beside(tmp / "frames", in_target_axes, target_faces, in_process, seconds, obj_bar), \
                concurrent.futures.ThreadPoolExecutor(1) as beside:
            # the GLB is array arithmetic and file writes, which release the GIL: it overlaps the rig and preview
            glb_written = None if options.no_glb else beside.submit(glb)
            if options.rig:
                with timed(seconds, "rig"):
                    write_rig(tmp, options, summary, target, target_faces, world, rig_source)
            if options.preview_frames:
                from aniformer.io.render import render_animation_gif

                shown = center_bbox(driving) if options.center else driving
                with tqdm(total=min(options.preview_frames, len(local)), unit="frame", desc="preview",
                          disable=options.no_progress, file=sys.stderr) as bar, timed(seconds, "preview"):
                    render_animation_gif([("driver", shown, driving_faces), ("result", world, target_faces)],
                                         tmp / "preview.gif", fps=fps, max_frames=options.preview_frames,
                                         progress=bar.update)
            if glb_written is not None:
                glb_written.result()  # its exception, if it raised
        (tmp / "animation.json").write_text(json.dumps(summary, indent=2) + "\n")


def write_animation(out: Path, options: AnimateOptions, state: dict, name: str, fps: float, driving,
                    driving_faces, target, target_faces, axes: dict, units: dict, inference: Inference, seconds: dict,
                    objs_process: bool = False, driving_animation: dict | None = None) -> dict:
    """Place the inferred frames in the world, then `write_outputs` into
    ``out`` with their animation.json record (returned), in the target's unit (``units``: {role: (unit, why)} as
    read); ``objs_process``: see `write_outputs`; ``driving_animation``: the glTF animation played as the driver
    (`aniformer.io.gltf_scene.GltfClip.record`), if it was one."""
    from aniformer.animate import root_motion

    local = inference.frames
    translation = None if options.center else root_motion(driving, local, inference.scale)
    registrations = inference.registrations
    summary = {
        "checkpoint": str(options.checkpoint), "target": str(options.target), "driving": str(options.driving),
        "name": name, "frames": len(local), "fps": fps, "unit": units["target"][0],
        **({"driving_animation": driving_animation} if driving_animation is not None else {}),
        "driving_vertices": int(driving.shape[1]), "target_vertices": int(target.shape[0]),
        "window": inference.window, "combine": inference.combine, "windows": inference.windows,
        "input_center": inference.input_center,
        "registered": {role: fit.record() for role, fit in registrations.items()},
        "up": {role: {"axis": axis, "why": why} for role, (axis, why) in axes.items()},
        "units": {role: {"unit": unit, "why": why} for role, (unit, why) in units.items()},
        "trust": inference.trust.to_dict(),
        "output_centred": options.center,
        "model": state["config"].get("model", {}), "epoch": state.get("epoch"),
        "seconds": seconds,
    }
    rig_source = rig_inputs(options, state, target, target_faces, registrations) if options.rig else None
    write_outputs(out, options, summary, driving, driving_faces, local, translation, target, target_faces, rig_source,
                  objs_process)
    return summary

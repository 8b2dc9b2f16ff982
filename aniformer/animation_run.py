"""One animation run below the jobs (no Ray, no MLflow): jobs/animate.py's options (`AnimateOptions`), its
inputs checked and turned z up, the meshes carried onto the topology the model runs on (`model_inputs`), and
the inference (`infer`). jobs/animate.py runs it all in one process (`animate_files`); pipeline/retarget.py
runs `infer` in an actor and `aniformer.animation_outputs.write_animation` in a task for each pair.
"""

from __future__ import annotations

import contextlib
import functools
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from aniformer.errors import UserError
from aniformer.io.glb import MAX_GLB_BYTES, MAX_MORPH_TARGETS
from aniformer.io.mesh import GLTF_SUFFIXES


@dataclass(frozen=True)
class AnimateOptions:
    """jobs/animate.py's flags as parsed, all but ``--out`` and ``--device`` (see its ``--help``)."""

    checkpoint: str
    target: str
    driving: str
    fps: float | None
    animation: str | None
    unit: str
    up: str
    name: str | None
    template: str | None
    combine: str
    input_center: str | None
    center: bool
    batch_size: int
    max_vertices: int
    max_frames: int
    frames_per_mesh: int
    no_glb: bool
    rig: bool
    bone_names: str
    preview_frames: int
    overwrite: bool
    force: bool
    no_progress: bool


def check_flags(options: AnimateOptions) -> None:
    """The numeric flags' ranges, before anything is loaded."""
    for flag, value, low in (("--batch-size", options.batch_size, 1), ("--max-vertices", options.max_vertices, 3),
                             ("--max-frames", options.max_frames, 1), ("--preview-frames", options.preview_frames, 0),
                             ("--frames-per-mesh", options.frames_per_mesh, 1)):
        if value < low:
            raise UserError(f"{flag} must be >= {low}, got {value}")
    if options.frames_per_mesh > MAX_MORPH_TARGETS:
        raise UserError(f"--frames-per-mesh {options.frames_per_mesh:,}: three.js cannot play more than "
                        f"{MAX_MORPH_TARGETS:,} morph targets per mesh")
    if options.fps is not None and not 0 < options.fps < float("inf"):
        raise UserError(f"--fps must be a positive number, got {options.fps}")
    if options.bone_names != "anny" and not options.rig:
        raise UserError("--bone-names names the rig's joints: add --rig")


def anny_topology(vertices, faces) -> str | None:
    """The Anny topology a mesh has (vertex count and faces), if any: the model runs there as it is."""
    import numpy as np

    from aniformer.synth.bodies import TOPOLOGIES, BodyModel

    for topology, count in TOPOLOGIES.items():
        if count == len(vertices) and np.array_equal(BodyModel(topology).faces, faces):
            return topology
    return None


def load_inputs(options: AnimateOptions):
    """(driving frame files, the animated glTF they are (`aniformer.animate.driving_clip`) or None, target vertices
    and faces, fps, name, {role: (unit, why)} of the target and the driver: ``--unit``, else the one their size
    is a body's in), all checked before any work (and before anything is written): frame count, the target mesh,
    the units, the size the GLB would have."""
    from aniformer.animate import driving_clip, driving_files, driving_fps, driving_frames, driving_unit
    from aniformer.io.mesh import load_body_mesh

    files = driving_files(options.driving)
    clip = driving_clip(files, options.fps, options.animation)
    frames = driving_frames(files, clip)
    if frames > options.max_frames:
        raise UserError(f"--driving {options.driving}: {frames:,} frames exceeds --max-frames "
                        f"{options.max_frames:,}")
    target, target_faces, target_unit = load_body_mesh(options.target, options.max_vertices, options.unit)
    fps = options.fps or driving_fps(files, clip) or 30.0
    name = options.name or f"{Path(options.target).stem}_{files[0].stem if clip is not None else files[0].parent.name}"
    check_glb_size(options, frames, target, target_faces)
    units = {"target": target_unit, "driver": driving_unit(files, clip, options.max_vertices, options.unit)}
    return files, clip, target, target_faces, fps, name, units


def check_glb_size(options: AnimateOptions, frames: int, target, target_faces) -> None:
    """`UserError` when animation.glb would be more than glTF clients load (and ``--no-glb`` is not given)."""
    from aniformer.io.glb import glb_size

    size = glb_size(frames, len(target), len(target_faces), options.frames_per_mesh)
    if size > MAX_GLB_BYTES and not options.no_glb:
        raise UserError(f"animation.glb would be {size / 2**30:.1f} GiB ({frames:,} frames x {len(target):,} "
                        "vertices); glTF clients load at most 2 GiB: cut the clip, or --no-glb for the OBJs only")


def input_axes(options: AnimateOptions, files, target_faces, target, driving, driving_faces) -> dict[str, tuple[str, str]]:
    """{role: (up axis, why)} of the target and the driver: ``--up``, else glTF's y, else the axis the body
    stands along (``aniformer.registration.detect_up``)."""
    return {"target": input_axis(options.up, Path(options.target), target[None], target_faces),
            "driver": input_axis(options.up, files[0], driving, driving_faces)}


def input_axis(up: str, path: Path, frames, faces) -> tuple[str, str]:
    """(up axis, why) of one mesh file's ``frames``, read with ``--up`` ``up`` (see `input_axes`)."""
    import numpy as np

    from aniformer.registration import detect_up

    convention = "y" if path.suffix.lower() in GLTF_SUFFIXES else "z"
    if up != "auto":
        return up, "--up"
    if convention == "y":
        return "y", "glTF is y-up"
    shown = frames[np.unique(np.linspace(0, len(frames) - 1, min(len(frames), 8)).round().astype(int))]
    return detect_up(shown, faces, convention)


@contextlib.contextmanager
def timed(seconds: dict, stage: str):
    """Adds the block's wall time to ``seconds[stage]`` (animation.json's per-stage breakdown)."""
    began = time.perf_counter()
    try:
        yield
    finally:
        seconds[stage] = round(seconds.get(stage, 0.0) + time.perf_counter() - began, 3)


def model_inputs(options: AnimateOptions, state: dict, config, driving, driving_faces, target, target_faces,
                 seconds: dict, registered: dict | None = None):
    """(faces, driving, target) on the topology the model runs on, the registrations that carry meshes of
    other topologies there (`aniformer.correspondence.Correspondence`, by role; none for an absolute-output
    model) and the driver's self-check where it was registered (`aniformer.trust.Trust`, else None).
    ``registered`` holds registrations already made for these meshes ({"target": Correspondence, "driver":
    (Correspondence, Trust)}, jobs/retarget.py's shared ones); the others are made here."""
    import numpy as np

    registrations, driver_trust = {}, None
    if getattr(config, "output", "absolute") == "absolute":  # no vertex correspondence needed
        return target_faces, driving, target, registrations, driver_trust
    from aniformer.correspondence import register_clip, register_mesh
    from aniformer.synth.bodies import TOPOLOGIES, BodyModel

    registered = registered or {}
    trained = (state["config"].get("data") or {}).get("topology")
    topology = options.template or anny_topology(driving[0], driving_faces) or trained
    if topology not in TOPOLOGIES:
        raise UserError(f"--template must be one of {', '.join(TOPOLOGIES)}; got {topology!r}")
    template = BodyModel(topology)
    faces = template.faces
    if "driver" in registered:
        registrations["driver"], driver_trust = registered["driver"]
    elif not np.array_equal(driving_faces, faces):  # another vertex count, order or connectivity
        with timed(seconds, "register driver"):
            registrations["driver"], driver_trust = register_clip(driving, driving_faces, topology)
        _report_fit("driver", registrations["driver"], template, seconds["register driver"])
    if "target" in registered:
        registrations["target"] = registered["target"]
    elif not np.array_equal(target_faces, faces):
        with timed(seconds, "register target"):
            registrations["target"] = register_mesh(target, target_faces, topology)
        _report_fit("target", registrations["target"], template, seconds["register target"])
    model_driving = registrations["driver"].to_template(driving) if "driver" in registrations else driving
    model_target = registrations["target"].unposed_template if "target" in registrations else target
    return faces, model_driving, model_target, registrations, driver_trust


def _report_fit(role: str, fit, template, seconds: float) -> None:
    props = fit.prop_record()
    print(f"registered the {role} ({len(fit.vertices):,} vertices) onto Anny {template.topology} "
          f"({template.num_vertices:,} vertices): {fit.rms * 1000:.1f} mm RMS surface distance, "
          f"{seconds:.1f} s{' (the fit of an earlier run, aniformer.registration.cached_fit)' if fit.fit_cached else ''}"
          + (f"; {props['parts']} separate part(s) beyond the body ({props['surface_share']:.1%} of its surface) "
             "carried rigidly as props" if props["parts"] else "")
          + (f"; kept the fit of sampling seed {fit.fit_seed} (aniformer.correspondence.register_mesh: the self-check "
             "refused an earlier one)" if fit.fit_seed else ""), file=sys.stderr)


@dataclass(frozen=True)
class Inference:
    """What `infer` made: the target's animated frames, and how they were made."""

    frames: object  # (frames, V, 3) the target animated, z up, bounding-box centred per frame
    combine: str  # how overlapping windows' frames were combined
    window: int  # frames per window
    windows: int
    input_center: str
    registrations: dict  # role ("target", "driver") -> the `Correspondence` that carried it to the model's topology
    trust: object  # the self-check's `aniformer.trust.Trust`
    scale: float  # the target's body size over the driver's (root motion is scaled by it)


def infer(options: AnimateOptions, model, state: dict, driving, driving_faces, target, target_faces, device,
          seconds: dict, registered: dict | None = None) -> Inference:
    """The target's animated frames (sliding windows of the model) and how they were made (each stage's
    time into ``seconds``; ``registered``: `model_inputs`)."""
    import numpy as np
    import torch
    from tqdm import tqdm

    from aniformer.animate import animate_sequence, body_scale, num_windows
    from aniformer.geometry import center_bbox
    from aniformer.trust import animation_trust

    config = model.config
    input_center = options.input_center or (state["config"].get("data") or {}).get("center", "mesh")
    faces, model_driving, model_target, registrations, driver_trust = model_inputs(options, state, config, driving,
                                                                              driving_faces, target, target_faces,
                                                                              seconds, registered)
    model = functools.partial(model.to(device), faces=torch.from_numpy(np.asarray(faces, np.int64)).to(device))
    outputs = config.output_frames()
    combine = options.combine if outputs == slice(None) else "center"
    window = config.window or len(driving)  # 0: the whole clip in one window (the skinned transfer)
    total = num_windows(len(driving), window, outputs, combine)
    stage = "skinned fit" if config.output == "skinned" else "network"
    if stage == "skinned fit":  # one window: its progress bar stands still for the whole fit
        print(f"skinned transfer: Anny's skeleton fitted to {len(driving):,} frames and the target at once "
              "(~0.6 s a frame on 2 CPU cores, docs/benchmarks.md)", file=sys.stderr)
    with tqdm(total=total, unit="window", desc="animate", disable=options.no_progress, file=sys.stderr) as bar, \
            timed(seconds, stage):
        result = animate_sequence(model, model_driving, model_target, window=window, outputs=outputs,
                                  combine=combine, center=input_center, batch_size=options.batch_size, device=device,
                                  progress=bar.update, force=options.force)
    if "target" in registrations:
        with timed(seconds, "carry back"):
            result = registrations["target"].from_template(result)
    if not np.isfinite(result).all():
        raise UserError(f"the model produced NaN or infinite coordinates ({options.checkpoint}: diverged weights?)")
    with timed(seconds, "self-check"):
        trust = animation_trust(result, target, target_faces, registrations.get("target"), driver_trust)
    scale = body_scale(target, target_faces, driving[0], driving_faces)
    result = center_bbox(result)  # the uncentred clip freed at once: one copy of it less at a time
    return Inference(result, combine, window, total, input_center, registrations, trust, scale)


def animate_files(options: AnimateOptions, inputs: tuple, out: Path, device, load_model: Callable[[], tuple],
                  start: float):
    """jobs/animate.py's run from its checked ``inputs`` (`load_inputs`, begun at ``start``, a ``perf_counter``
    time): ``load_model()``, the driving frames loaded, `infer`, the result refused if the self-check does not
    trust it (unless ``--force``), else written into ``out`` (`aniformer.animation_outputs.write_animation`).
    (Its animation.json record, the self-check's ``Trust``, seconds of inference.)"""
    from tqdm import tqdm

    from aniformer.animate import driving_frames, load_driving
    from aniformer.animation_outputs import write_animation  # it imports this module
    from aniformer.geometry import to_z_up

    files, clip, target, target_faces, fps, name, units = inputs
    model, state = load_model()
    with tqdm(total=driving_frames(files, clip), unit="frame", desc="load driving",
              disable=options.no_progress, file=sys.stderr) as bar:
        driving, driving_faces = load_driving(files, options.max_vertices, units["driver"][0], progress=bar.update,
                                              clip=clip)
    axes = input_axes(options, files, target_faces, target, driving, driving_faces)
    target, driving = to_z_up(target, axes["target"][0]), to_z_up(driving, axes["driver"][0])
    loaded = time.perf_counter()
    seconds = {"load": round(loaded - start, 3)}
    inference = infer(options, model, state, driving, driving_faces, target, target_faces, device, seconds)
    trust = inference.trust
    if not trust.ok and not options.force:
        raise UserError(f"the self-check does not trust the result, nothing written: {trust.reason()}; check the "
                        f"inputs' up axis (read as {axes['target'][0]} for the target, {axes['driver'][0]} for the "
                        "driver: --up) and that both are whole human bodies, or pass --force to write it anyway")
    inferred = time.perf_counter()
    seconds["inference"] = round(inferred - loaded, 3)
    summary = write_animation(out, options, state, name, fps, driving, driving_faces, target, target_faces, axes,
                              units, inference, seconds, objs_process=True,
                              driving_animation=clip.record() if clip is not None else None)
    return summary, trust, inferred - loaded

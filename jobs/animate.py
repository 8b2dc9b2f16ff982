"""Animate a target mesh with a driving mesh sequence of any length using a trained checkpoint.

    python jobs/animate.py --target me.obj --driving clips/jump/ --out anim/jump     # the shipped model
    python jobs/animate.py --checkpoint runs/tiny/best.pt --target me.obj --driving clips/jump/ --out anim/jump
    python jobs/animate.py --checkpoint 3f2a...c9 --target me.ply --driving 'clips/run/frame_*.obj' --out anim/run
    python jobs/animate.py --checkpoint models:/aniformer/latest --target me.obj --driving clips/jump/ --out anim/jump

``--driving`` is a directory of OBJ/PLY/... frames or a glob, in natural order (frame_2 before
frame_10); every frame must have the first frame's vertices and faces. Target and driver may have
any vertex count, order and connectivity: a mesh that is not the model's Anny topology is first
registered onto it (aniformer/registration.py: Anny's body fitted to the mesh, a few seconds; the
result is carried back to the mesh's own vertices). The model runs on the driver's topology when
that is one of Anny's, else on the checkpoint's (``--template``); a driver that is not an Anny
mesh is registered on up to three frames spread over the clip. Inputs are human bodies in any
pose and orientation, z or y up (``--up``), in ``--unit`` (default m); a result the self-check
does not trust is refused (``--force`` writes it anyway). A T-frame window slides over the sequence
one frame at a time; overlapping predictions of a frame are averaged (``--combine mean``) or the
window centred on it is used (``--combine center``, always for a regression-head model); see
docs/animate.md. The result is placed in world space where the driver is (its root motion, scaled
to the target's height, feet on the driver's floor); ``--center`` keeps every frame bounding-box
centred instead.

Outputs in ``--out``: frames/frame_NNNN.obj (one per driving frame, in the target's unit and axes),
animation.glb (glTF 2.0: y up, metres, morph targets, lasting N / fps), preview.gif (driver |
result) and animation.json (what was done); with ``--rig`` also rigged.glb (the target skinned to
Anny's skeleton, the clip as joint rotations) and motion.bvh (aniformer/rig.py). They are written under a temporary name beside
``--out`` and renamed into place when complete; an existing non-empty ``--out`` is refused unless
``--overwrite``. Bad input (unreadable/garbage/empty meshes, NaN, coordinates beyond 1 km, bad
faces, driving frames with other faces, meshes over ``--max-vertices``, a checkpoint that does not
match its config) stops with one line, exit 2.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import sys
import tempfile
import time
from pathlib import Path

from aniformer.animate import FPS_SIDECARS
from aniformer.cli import ArgumentParser, resolve_device, run
from aniformer.errors import UserError
from aniformer.files import claim_output, releases_locks, staged_output_dir
from aniformer.glb import FRAMES_PER_MESH, MAX_GLB_BYTES, MAX_MORPH_TARGETS
from aniformer.mesh import DEFAULT_MAX_VERTICES, GLTF_SUFFIXES, UNITS, UP_AXES


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = ArgumentParser(prog="animate.py", description=__doc__.split("\n\n")[0],
                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--checkpoint", default="pretrained", metavar="CKPT",
                   help="checkpoint file, MLflow run id, registered model (models:/NAME/latest, models:/NAME/VERSION, "
                        "models:/NAME@ALIAS), or 'pretrained' (the default: the shipped model, docs/model_card.md)")
    p.add_argument("--target", required=True, metavar="MESH", help="the mesh to animate (OBJ, PLY, ...)")
    p.add_argument("--driving", required=True, metavar="DIR_OR_GLOB", help="driving frames: a directory or a glob")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--fps", type=float, default=None,
                   help=f"frame rate of the sequence (default: the driver's, from {' or '.join(FPS_SIDECARS)} "
                        "beside its frames, else 30)")
    p.add_argument("--unit", choices=tuple(UNITS), default="m", help="unit of the target and driving files (default m)")
    p.add_argument("--up", choices=("auto", *UP_AXES), default="auto",
                   help="the axis the inputs stand along (default auto: the axis the body stands along, else the "
                        "format's: y for glTF, z for the others); outputs are written in the target's axes")
    p.add_argument("--name", default=None,
                   help="name of the glTF node, mesh and animation (default: TARGET_DRIVING from the file names)")
    p.add_argument("--template", metavar="TOPOLOGY",
                   help="Anny topology the model runs on, meshes of other topologies registered onto it "
                        "(default: the driver's when it is an Anny mesh, else the checkpoint's)")
    p.add_argument("--combine", choices=("mean", "center"), default="mean",
                   help="how overlapping windows combine (default: mean)")
    p.add_argument("--input-center", choices=("mesh", "window", "none"), default=None,
                   help="how the model's inputs are centred (default: the checkpoint's data.center, as in training)")
    p.add_argument("--center", action="store_true",
                   help="keep every output frame bounding-box centred (no root motion)")
    p.add_argument("--batch-size", type=int, default=8, help="windows per forward pass")
    p.add_argument("--max-vertices", type=int, default=DEFAULT_MAX_VERTICES,
                   help=f"refuse meshes with more vertices (default {DEFAULT_MAX_VERTICES:,})")
    p.add_argument("--max-frames", type=int, default=10_000, help="refuse longer driving sequences (default 10,000)")
    p.add_argument("--frames-per-mesh", type=int, default=FRAMES_PER_MESH,
                   help=f"morph targets per glTF mesh, the clip is split beyond (default {FRAMES_PER_MESH}; "
                        f"three.js plays at most {MAX_MORPH_TARGETS:,})")
    p.add_argument("--no-glb", action="store_true", help="write no animation.glb (e.g. a clip too large for glTF)")
    p.add_argument("--rig", action="store_true",
                   help="also write rigged.glb (the target skinned to Anny's skeleton, the clip as joint rotations) "
                        "and motion.bvh (the same skeleton and motion)")
    p.add_argument("--bone-names", choices=("anny", "mixamo"), default="anny",
                   help="the rig's joint names: Anny's bone labels, or Mixamo's (mixamorig:Hips ...) where Mixamo has "
                        "the bone (default anny)")
    p.add_argument("--preview-frames", type=int, default=60,
                   help="frames drawn in preview.gif, evenly spaced (default 60; 0 = no preview)")
    p.add_argument("--device", default="auto", help="cpu, cuda, cuda:1 ... (default: cuda if available)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing non-empty --out")
    p.add_argument("--force", action="store_true",
                   help="animate even when the estimated time is over 2 h, and write a result the self-check refuses")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p.parse_args(argv)


def anny_topology(vertices, faces) -> str | None:
    """The Anny topology a mesh has (vertex count and faces), if any: the model runs there as it is."""
    import numpy as np

    from aniformer.synth.bodies import TOPOLOGIES, BodyModel

    for topology, count in TOPOLOGIES.items():
        if count == len(vertices) and np.array_equal(BodyModel(topology).faces, faces):
            return topology
    return None


def check_flags(args: argparse.Namespace) -> None:
    """The numeric flags' ranges, before anything is loaded."""
    for flag, value, low in (("--batch-size", args.batch_size, 1), ("--max-vertices", args.max_vertices, 3),
                             ("--max-frames", args.max_frames, 1), ("--preview-frames", args.preview_frames, 0),
                             ("--frames-per-mesh", args.frames_per_mesh, 1)):
        if value < low:
            raise UserError(f"{flag} must be >= {low}, got {value}")
    if args.frames_per_mesh > MAX_MORPH_TARGETS:
        raise UserError(f"--frames-per-mesh {args.frames_per_mesh:,}: three.js cannot play more than "
                        f"{MAX_MORPH_TARGETS:,} morph targets per mesh")
    if args.fps is not None and not 0 < args.fps < float("inf"):
        raise UserError(f"--fps must be a positive number, got {args.fps}")
    if args.bone_names != "anny" and not args.rig:
        raise UserError("--bone-names names the rig's joints: add --rig")


def load_inputs(args):
    """(driving frame files, target vertices and faces, fps, name), all checked before any work (and before
    anything is written): frame count, the target mesh, the size the GLB would have."""
    from aniformer.animate import driving_files, driving_fps
    from aniformer.mesh import load_mesh

    files = driving_files(args.driving)
    if len(files) > args.max_frames:
        raise UserError(f"--driving {args.driving}: {len(files):,} frames exceeds --max-frames {args.max_frames:,}")
    target, target_faces = load_mesh(args.target, max_vertices=args.max_vertices, unit=args.unit)
    fps = args.fps or driving_fps(files) or 30.0
    name = args.name or f"{Path(args.target).stem}_{files[0].parent.name}"
    check_glb_size(args, len(files), target, target_faces)
    return files, target, target_faces, fps, name


def check_glb_size(args, frames: int, target, target_faces) -> None:
    """`UserError` when animation.glb would be more than glTF clients load (and ``--no-glb`` is not given)."""
    from aniformer.glb import glb_size

    size = glb_size(frames, len(target), len(target_faces), args.frames_per_mesh)
    if size > MAX_GLB_BYTES and not args.no_glb:
        raise UserError(f"animation.glb would be {size / 2**30:.1f} GiB ({frames:,} frames x {len(target):,} "
                        "vertices); glTF clients load at most 2 GiB: cut the clip, or --no-glb for the OBJs only")


def input_axes(args, files, target_faces, target, driving, driving_faces) -> dict[str, tuple[str, str]]:
    """{role: (up axis, why)} of the target and the driver: ``--up``, else glTF's y, else the axis the body
    stands along (``aniformer.registration.detect_up``)."""
    return {"target": input_axis(args.up, Path(args.target), target[None], target_faces),
            "driver": input_axis(args.up, files[0], driving, driving_faces)}


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


def model_inputs(args, state: dict, config, driving, driving_faces, target, target_faces, seconds: dict,
                 registered: dict | None = None):
    """(faces, driving, target) on the topology the model runs on, the registrations that carry meshes of
    other topologies there (`aniformer.registration.Correspondence`, by role; none for an absolute-output
    model) and the driver's self-check where it was registered (`aniformer.trust.Trust`, else None).
    ``registered`` holds registrations already made for these meshes ({"target": Correspondence, "driver":
    (Correspondence, Trust)}, jobs/retarget.py's shared ones); the others are made here."""
    import numpy as np

    registrations, driver_trust = {}, None
    if getattr(config, "output", "absolute") == "absolute":  # no vertex correspondence needed
        return target_faces, driving, target, registrations, driver_trust
    from aniformer.registration import Correspondence, register_clip
    from aniformer.synth.bodies import TOPOLOGIES, BodyModel

    registered = registered or {}
    trained = (state["config"].get("data") or {}).get("topology")
    topology = args.template or anny_topology(driving[0], driving_faces) or trained
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
            registrations["target"] = Correspondence(target, target_faces, topology)
        _report_fit("target", registrations["target"], template, seconds["register target"])
    model_driving = registrations["driver"].to_template(driving) if "driver" in registrations else driving
    model_target = registrations["target"].template if "target" in registrations else target
    return faces, model_driving, model_target, registrations, driver_trust


def _report_fit(role: str, fit, template, seconds: float) -> None:
    print(f"registered the {role} ({len(fit.vertices):,} vertices) onto Anny {template.topology} "
          f"({template.num_vertices:,} vertices): {fit.rms * 1000:.1f} mm RMS surface distance, "
          f"{seconds:.1f} s", file=sys.stderr)


def rig_inputs(args, state: dict, target, target_faces, registrations: dict):
    """(the target's vertices on an Anny topology, that topology, where each target vertex lies on it or None)
    for ``aniformer.rig.build_rig``: the registration's, else the target itself when it is an Anny mesh, else
    a registration made here (a model of absolute output registers nothing)."""
    from aniformer.registration import Correspondence

    if "target" in registrations:
        fit = registrations["target"]
        return fit.template, fit.topology, fit.mesh_on_template
    topology = anny_topology(target, target_faces)
    if topology is not None:
        return target, topology, None
    fit = Correspondence(target, target_faces, args.template or (state["config"].get("data") or {}).get("topology"))
    return fit.template, fit.topology, fit.mesh_on_template


def write_rig(tmp: Path, args, summary: dict, target, target_faces, world, rig_source) -> None:
    """rigged.glb and motion.bvh of the animated ``world`` frames; the rig's size and fit into ``summary``."""
    from aniformer.bvh import write_bvh
    from aniformer.glb import write_rigged_glb
    from aniformer.rig import build_rig, fit_rig

    rig, motion = fit_rig(build_rig(target, *rig_source, bone_names=args.bone_names), target, world)
    write_rigged_glb(tmp / "rigged.glb", target, target_faces, rig, motion, fps=summary["fps"], name=summary["name"],
                     extras={"checkpoint": str(args.checkpoint), "driving": str(args.driving)})
    write_bvh(tmp / "motion.bvh", rig, motion, summary["fps"], UNITS[args.unit])
    summary["rig"] = {"joints": len(rig.names), "residual_m": round(motion.residual, 6)}


def write_outputs(out: Path, args, summary: dict, driving, driving_faces, local, translation, target, target_faces,
                  rig_source) -> None:
    """frames/*.obj, animation.glb, preview.gif, animation.json and with ``--rig`` rigged.glb and motion.bvh (of
    ``rig_source``: ``rig_inputs``), staged: `out` appears complete or not at all. Each one's time goes into
    ``summary["seconds"]``."""
    from tqdm import tqdm

    from aniformer.animate import write_obj
    from aniformer.glb import write_glb
    from aniformer.mesh import center_bbox, from_z_up

    seconds = summary["seconds"]
    world = local if translation is None else local + translation[:, None]
    fps, name = summary["fps"], summary["name"]
    with staged_output_dir(out, args.overwrite) as tmp:
        digits = max(4, len(str(len(local) - 1)))
        (tmp / "frames").mkdir()
        in_target_axes = from_z_up(world, summary["up"]["target"]["axis"]) / UNITS[args.unit]
        with timed(seconds, "write OBJ"):
            for k, vertices in enumerate(tqdm(in_target_axes, unit="obj", desc="write OBJ",
                                              disable=args.no_progress, file=sys.stderr)):
                write_obj(tmp / "frames" / f"frame_{k:0{digits}d}.obj", vertices, target_faces)
        if not args.no_glb:
            with timed(seconds, "write GLB"):
                write_glb(tmp / "animation.glb", local, target_faces, fps=fps, name=name, translation=translation,
                          frames_per_mesh=args.frames_per_mesh,
                          extras={"checkpoint": str(args.checkpoint), "driving": str(args.driving)})
        if args.rig:
            with timed(seconds, "rig"):
                write_rig(tmp, args, summary, target, target_faces, world, rig_source)
        if args.preview_frames:
            from aniformer.render import render_animation_gif

            shown = center_bbox(driving) if args.center else driving
            with tqdm(total=min(args.preview_frames, len(local)), unit="frame", desc="preview",
                      disable=args.no_progress, file=sys.stderr) as bar, timed(seconds, "preview"):
                render_animation_gif([("driver", shown, driving_faces), ("result", world, target_faces)],
                                     tmp / "preview.gif", fps=fps, max_frames=args.preview_frames,
                                     progress=bar.update)
        (tmp / "animation.json").write_text(json.dumps(summary, indent=2) + "\n")


def infer(args, model, state: dict, driving, driving_faces, target, target_faces, device, seconds: dict,
          registered: dict | None = None):
    """The target's animated frames (sliding windows of the model) and how they were made (each stage's
    time into ``seconds``; ``registered``: `model_inputs`):
    (frames, combine, windows, input_center, registrations, the self-check's ``Trust``, the size of the
    target's body over the driver's)."""
    import numpy as np
    import torch
    from tqdm import tqdm

    from aniformer.animate import animate_sequence, body_scale, num_windows
    from aniformer.trust import animation_trust

    config = model.config
    input_center = args.input_center or (state["config"].get("data") or {}).get("center", "mesh")
    faces, model_driving, model_target, registrations, driver_trust = model_inputs(args, state, config, driving,
                                                                              driving_faces, target, target_faces,
                                                                              seconds, registered)
    model = functools.partial(model.to(device), faces=torch.from_numpy(np.asarray(faces, np.int64)).to(device))
    outputs = config.output_frames()
    combine = args.combine if outputs == slice(None) else "center"
    total = num_windows(len(driving), config.window, outputs, combine)
    with tqdm(total=total, unit="window", desc="animate", disable=args.no_progress, file=sys.stderr) as bar, \
            timed(seconds, "network"):
        result = animate_sequence(model, model_driving, model_target, window=config.window, outputs=outputs,
                                  combine=combine, center=input_center, batch_size=args.batch_size, device=device,
                                  progress=bar.update, force=args.force)
    if "target" in registrations:
        with timed(seconds, "carry back"):
            result = registrations["target"].from_template(result)
    if not np.isfinite(result).all():
        raise UserError(f"the model produced NaN or infinite coordinates ({args.checkpoint}: diverged weights?)")
    with timed(seconds, "self-check"):
        trust = animation_trust(result, target, target_faces, registrations.get("target"), driver_trust)
    scale = body_scale(target, target_faces, driving[0], driving_faces)
    return result, combine, total, input_center, registrations, trust, scale


def local_checkpoint(checkpoint: str, scratch: Path) -> Path:
    """The checkpoint file of ``checkpoint`` (resolved by `resolve_pretrained`): the file itself, else a run id's
    or registered model's, downloaded into ``scratch``."""
    local = Path(checkpoint).expanduser()
    if not local.exists():  # a run id or model URI: only then MLflow (~1.5 s of imports)
        from pipeline.registry import resolve_checkpoint

        local = resolve_checkpoint(checkpoint, scratch)
    return local


def write_animation(out: Path, args, state: dict, window: int, name: str, fps: float, driving, driving_faces, target,
                    target_faces, axes: dict, inference: tuple, seconds: dict) -> dict:
    """Place the inferred frames (``inference``: what `infer` returns) in the world, then `write_outputs` into
    ``out`` with their animation.json record (returned)."""
    from aniformer.animate import root_motion
    from aniformer.mesh import center_bbox

    result, combine, total, input_center, registrations, trust, scale = inference
    local = center_bbox(result)
    translation = None if args.center else root_motion(driving, local, scale)
    summary = {
        "checkpoint": str(args.checkpoint), "target": str(args.target), "driving": str(args.driving),
        "name": name, "frames": len(result), "fps": fps, "unit": args.unit,
        "driving_vertices": int(driving.shape[1]), "target_vertices": int(target.shape[0]),
        "window": window, "combine": combine, "windows": total, "input_center": input_center,
        "registered": {role: {"rms_m": round(fit.rms, 5), "template_vertices": len(fit.template)}
                       for role, fit in registrations.items()},
        "up": {role: {"axis": axis, "why": why} for role, (axis, why) in axes.items()},
        "trust": trust.to_dict(),
        "output_centred": args.center,
        "model": state["config"].get("model", {}), "epoch": state.get("epoch"),
        "seconds": seconds,
    }
    rig_source = rig_inputs(args, state, target, target_faces, registrations) if args.rig else None
    write_outputs(out, args, summary, driving, driving_faces, local, translation, target, target_faces, rig_source)
    return summary


@releases_locks
def main(argv: list[str]) -> None:
    args = parse_args(argv)
    check_flags(args)
    out = Path(args.out).expanduser().resolve()
    from aniformer.checkpoint import resolve_pretrained  # torch: after the arguments are checked

    checkpoint = resolve_pretrained(args.checkpoint)
    claim_output(out, args.overwrite, {"--checkpoint": checkpoint, "--target": args.target, "--driving": args.driving})
    device = resolve_device(args.device)

    from tqdm import tqdm

    from aniformer.animate import load_driving
    from aniformer.checkpoint import model_from_checkpoint
    from aniformer.mesh import to_z_up

    start = time.perf_counter()
    files, target, target_faces, fps, name = load_inputs(args)  # bad input fails before any work
    with tempfile.TemporaryDirectory(prefix="aniformer-animate-") as scratch:
        model, state = model_from_checkpoint(local_checkpoint(checkpoint, Path(scratch)))
    with tqdm(total=len(files), unit="frame", desc="load driving", disable=args.no_progress, file=sys.stderr) as bar:
        driving, driving_faces = load_driving(files, args.max_vertices, args.unit, progress=bar.update)
    axes = input_axes(args, files, target_faces, target, driving, driving_faces)
    target, driving = to_z_up(target, axes["target"][0]), to_z_up(driving, axes["driver"][0])
    loaded = time.perf_counter()
    seconds = {"load": round(loaded - start, 3)}
    result, combine, total, input_center, registrations, trust, scale = infer(args, model, state, driving, driving_faces,
                                                                              target, target_faces, device, seconds)
    if not trust.ok and not args.force:
        raise UserError(f"the self-check does not trust the result, nothing written: {trust.reason()}; check the "
                        f"inputs' up axis (read as {axes['target'][0]} for the target, {axes['driver'][0]} for the "
                        "driver: --up) and that both are whole human bodies, or pass --force to write it anyway")
    inferred = time.perf_counter()
    seconds["inference"] = round(inferred - loaded, 3)
    inference = result, combine, total, input_center, registrations, trust, scale
    summary = write_animation(out, args, state, model.config.window, name, fps, driving, driving_faces, target,
                              target_faces, axes, inference, seconds)
    seconds = time.perf_counter() - start
    window = model.config.window
    worst = max(trust.checks, key=lambda c: c.value / c.limit)
    if trust.ok:
        print(f"self-check: trusted (closest to its limit: {worst.name} {worst.value:.3f} of {worst.limit:.3f})")
    else:
        print(f"warning: written with --force, the self-check does not trust it: {trust.reason()}", file=sys.stderr)
    print(f"animated {len(result)} frames ({target.shape[0]:,}-vertex target, {driving.shape[1]:,}-vertex driver, "
          f"T={window}, {total} windows, combine={combine}) in {seconds:.1f} s "
          f"(inference {inferred - loaded:.1f} s)")
    print(f"frames: {out / 'frames'}/ ({len(result)} OBJ)")
    if not args.no_glb:
        print(f"animation: {out / 'animation.glb'} ({len(result)} frames at {fps:g} fps, {len(result) / fps:.2f} s)")
    if args.preview_frames:
        print(f"preview: {out / 'preview.gif'}")
    if args.rig:
        rig = summary["rig"]
        print(f"rig: {out / 'rigged.glb'} and {out / 'motion.bvh'} ({rig['joints']} joints, skinning "
              f"{rig['residual_m'] * 1000:.1f} mm RMS from the frames)")


def cli() -> None:
    """The ``aniformer-animate`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()

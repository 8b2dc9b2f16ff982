"""Animate a target mesh with a driving mesh sequence of any length using a trained checkpoint.

    python jobs/animate.py --target me.obj --driving clips/jump/ --out anim/jump     # the shipped model
    python jobs/animate.py --checkpoint runs/tiny/best.pt --target me.obj --driving clips/jump/ --out anim/jump
    python jobs/animate.py --checkpoint 3f2a...c9 --target me.ply --driving 'clips/run/frame_*.obj' --out anim/run
    python jobs/animate.py --checkpoint models:/aniformer/latest --target me.obj --driving clips/jump/ --out anim/jump
    python jobs/animate.py --checkpoint skinned --target me.obj --driving clips/jump/ --out anim/jump   # no network

``--driving`` is a directory of OBJ/PLY/... frames or a glob, in natural order (frame_2 before
frame_10); every frame must have the first frame's vertices and faces. Target and driver may have
any vertex count, order and connectivity: a mesh that is not the model's Anny topology is first
registered onto it (aniformer/registration.py: Anny's body fitted to the mesh, a few seconds; the
result is carried back to the mesh's own vertices). The model runs on the driver's topology when
that is one of Anny's, else on the checkpoint's (``--template``); a driver that is not an Anny
mesh is registered on up to three frames spread over the clip. Inputs are human bodies in any
pose and orientation, z or y up (``--up``), in m, cm or mm (``--unit``, default auto: told apart
by the body's size); a result the self-check does not trust is refused (``--force`` writes it
anyway). A T-frame window slides over the sequence
one frame at a time; overlapping predictions of a frame are averaged (``--combine mean``) or the
window centred on it is used (``--combine center``, always for a regression-head model); see
docs/animate.md. The result is placed in world space where the driver is (its root motion, scaled
to the target's height, feet on the driver's floor); ``--center`` keeps every frame bounding-box
centred instead.

Outputs in ``--out``: frames/frame_NNNN.obj (one per driving frame, in the target's unit and axes),
animation.glb (glTF 2.0: y up, metres, morph targets, lasting N / fps), preview.gif (driver |
result) and animation.json (what was done); with ``--rig`` also rigged.glb (the target skinned to
Anny's skeleton, the clip as joint rotations) and motion.bvh (aniformer/rig.py, aniformer/rig_motion.py).
They are written under a temporary name beside ``--out`` and renamed into place when complete; an existing
non-empty ``--out`` is refused unless ``--overwrite``. Bad input (unreadable/garbage/empty meshes, NaN,
coordinates beyond 1 km, bad faces, driving frames with other faces, meshes over ``--max-vertices``, a checkpoint that does not
match its config) stops with one line, exit 2.
"""

from __future__ import annotations

import argparse
import functools
import sys
import tempfile
import time
from pathlib import Path

from aniformer.animate import FPS_SIDECARS
from aniformer.animation_run import AnimateOptions, animate_files, check_flags, load_inputs
from aniformer.cli.args import ArgumentParser, options_from, resolve_device
from aniformer.cli.exits import run
from aniformer.cli.locks import releases_locks
from aniformer.cli.outputs import claim_output
from aniformer.geometry import STANDS_ALONG, UP_AXES
from aniformer.io.glb import FRAMES_PER_MESH, MAX_MORPH_TARGETS
from aniformer.io.mesh import DEFAULT_MAX_VERTICES, UNITS


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = ArgumentParser(prog="animate.py", description=__doc__.split("\n\n")[0],
                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--checkpoint", default="pretrained", metavar="CKPT",
                   help="checkpoint file, MLflow run id, registered model (models:/NAME/latest, models:/NAME/VERSION, "
                        "models:/NAME@ALIAS), 'pretrained' (the default: the shipped model, docs/model_card.md), or "
                        "'skinned': no network, Anny's skeleton fitted to every frame and played on the target's "
                        "(6-24x closer than the shipped model on test clips, docs/results.md; ~0.6 s per frame on "
                        "2 cores)")
    p.add_argument("--target", required=True, metavar="MESH", help="the mesh to animate (OBJ, PLY, ...)")
    p.add_argument("--driving", required=True, metavar="DIR_OR_GLOB",
                   help="driving frames: a directory or a glob, or one animated glTF (.glb/.gltf)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--fps", type=float, default=None,
                   help=f"frame rate of the sequence (default: the driver's, from {' or '.join(FPS_SIDECARS)} "
                        "beside its frames or an animated glTF's own, else 30; an animated glTF is sampled at it)")
    p.add_argument("--animation", default=None, metavar="NAME",
                   help="with one animated glTF as --driving: the animation to play, by name or index (default: "
                        "its first)")
    p.add_argument("--unit", choices=("auto", *UNITS), default="auto",
                   help="unit of the target and driving files (default auto: for each, the one of m, cm, mm its "
                        "body's size is a human's in); outputs are written in the target's")
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


def local_checkpoint(checkpoint: str, scratch: Path) -> Path:
    """The checkpoint file of ``checkpoint`` (resolved by `resolve_pretrained`): the file itself, else a run id's
    or registered model's, downloaded into ``scratch``."""
    local = Path(checkpoint).expanduser()
    if not local.exists():  # a run id or model URI: only then MLflow (~1.5 s of imports)
        from pipeline.registry import resolve_checkpoint

        local = resolve_checkpoint(checkpoint, scratch)
    return local


def load_model(checkpoint: str):
    """(model, state) of ``checkpoint`` (resolved by `resolve_pretrained`), downloaded first where it is not a file;
    ``skinned``: the skinned transfer, no network (aniformer/skinned_transfer.py)."""
    from aniformer.checkpoint import model_from_checkpoint
    from aniformer.skinned_transfer import REFERENCE, skinned_model

    if checkpoint == REFERENCE:
        return skinned_model()
    with tempfile.TemporaryDirectory(prefix="aniformer-animate-") as scratch:
        return model_from_checkpoint(local_checkpoint(checkpoint, Path(scratch)))


@releases_locks
def main(argv: list[str]) -> None:
    args = parse_args(argv)
    options = options_from(AnimateOptions, args)
    check_flags(options)
    out = Path(args.out).expanduser().resolve()
    start = time.perf_counter()
    inputs = load_inputs(options)  # a missing or bad target or clip is refused before torch's seconds of imports
    from aniformer.checkpoint import resolve_pretrained

    checkpoint = resolve_pretrained(args.checkpoint)
    claim_output(out, args.overwrite, {"--checkpoint": checkpoint, "--target": args.target, "--driving": args.driving})
    device = resolve_device(args.device)
    summary, trust, inference = animate_files(options, inputs, out, device, functools.partial(load_model, checkpoint),
                                              start)
    seconds = time.perf_counter() - start
    frames, fps = summary["frames"], summary["fps"]
    worst = max(trust.checks, key=lambda c: c.value / c.limit)
    if trust.ok:
        print(f"self-check: trusted (closest to its limit: {worst.name} {worst.value:.3f} of {worst.limit:.3f})")
    else:
        print(f"warning: written with --force, the self-check does not trust it: {trust.reason()}", file=sys.stderr)
    print(f"animated {frames} frames ({summary['target_vertices']:,}-vertex target, {summary['driving_vertices']:,}-vertex "
          f"driver, T={summary['window']}, {summary['windows']} windows, combine={summary['combine']}) in {seconds:.1f} s "
          f"(inference {inference:.1f} s)")
    if "driving_animation" in summary:
        played = summary["driving_animation"]
        print(f"driver: animation {played['name']!r} ({played['index'] + 1} of {played['of']}) of {args.driving}, "
              f"sampled at {played['fps']:g} fps" + (" (--animation to choose another)" if played["of"] > 1 else ""))
    for role, up in summary["up"].items():
        if up["why"] == STANDS_ALONG.format("y"):  # read from the body, against OBJ's z: say so
            print(f"read the {role} as y-up ({up['why']}); --up z if it lies along y in a z-up file")
    for role, unit in summary["units"].items():
        if unit["unit"] != "m":
            print(f"read the {role} in {unit['unit']} ({unit['why']}); outputs in the target's unit")
    print(f"frames: {out / 'frames'}/ ({frames} OBJ)")
    if not args.no_glb:
        print(f"animation: {out / 'animation.glb'} ({frames} frames at {fps:g} fps, {frames / fps:.2f} s)")
    if args.preview_frames:
        print(f"preview: {out / 'preview.gif'}")
    if args.rig:
        print(f"rig: {out / 'rigged.glb'} and {out / 'motion.bvh'} ({summary['rig']['joints']} joints, skinning "
              f"{summary['rig']['residual_m'] * 1000:.1f} mm RMS from the frames)")


def cli() -> None:
    """The ``aniformer-animate`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()

"""Retarget a motion library: every target mesh x every driving clip, as one Ray job.

    python jobs/retarget.py --targets characters/ --clips clips/ --out library/
    python jobs/retarget.py --targets characters/ --clips clips/ --out library/ --rig --checkpoint models:/aniformer/latest
    ray job submit --working-dir . -- python jobs/retarget.py --targets /shared/chars --clips /shared/clips --out /shared/lib

``--targets`` is a folder of meshes (OBJ, PLY, GLB, ...), ``--clips`` a folder whose sub-folders are driving
sequences (each what jobs/animate.py's ``--driving`` takes) and whose animated .glb/.gltf files are clips too
(a file of several animations one clip per animation, ``<stem>_<animation>``). Each pair gets ``OUT/<target stem>/<clip>/`` with
what jobs/animate.py writes for that pair alone (frames/, animation.glb, preview.gif, animation.json; with
``--rig`` rigged.glb and motion.bvh), staged and renamed into place when complete; ``OUT/summary.csv`` has a
row per pair: target, clip, status (ok, refused by the self-check, error), frames, seconds, fit error (mm),
self-check. Each target and clip is read once, and registered once where its topology is not the model's
(docs/retarget.md); the model is loaded once per actor (``--actors``).

A failing pair does not stop the others: its row says why and the job exits 2 at the end. Running the same
command again resumes: pairs whose outputs are complete are skipped, the others (failed, refused,
interrupted) are done. Without RAY_ADDRESS a local Ray instance is started (on 127.0.0.1 only); with it,
or under ``ray job submit``, the job runs on that cluster, whose nodes must all see the input and output
paths. The run is logged to MLflow as ``retarget-<OUT name>`` (``--no-mlflow`` to skip).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from aniformer.animation_run import AnimateOptions
from aniformer.cli.args import ArgumentParser, options_from
from aniformer.cli.exits import run
from aniformer.cli.locks import lock_output, releases_locks
from aniformer.cli.outputs import protect_inputs
from aniformer.errors import UserError
from aniformer.geometry import UP_AXES
from aniformer.io.mesh import DEFAULT_MAX_VERTICES, UNITS
from jobs import animate
from pipeline.motion_library import ClipSource, find_library, log_run, pair_line, write_summary


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = ArgumentParser(prog="retarget.py", description=__doc__.split("\n\n")[0],
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--targets", required=True, metavar="DIR", help="folder of target meshes")
    p.add_argument("--clips", required=True, metavar="DIR",
                   help="folder of driving clips: a sub-folder of frames, or an animated .glb/.gltf, each")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (OUT/<target stem>/<clip>/)")
    p.add_argument("--checkpoint", default="pretrained", metavar="CKPT",
                   help="as jobs/animate.py's: a file, an MLflow run id, a registered model, 'pretrained' (default) or "
                        "'skinned' (no network: Anny's skeleton fitted to every frame)")
    p.add_argument("--rig", action="store_true", help="also write rigged.glb and motion.bvh for every pair")
    p.add_argument("--bone-names", choices=("anny", "mixamo"), default="anny",
                   help="the rig's joint names, as jobs/animate.py's (default anny)")
    p.add_argument("--force", action="store_true", help="write results the self-check does not trust")
    p.add_argument("--unit", choices=("auto", *UNITS), default="auto",
                   help="unit of every input file (default auto: each file's, from its body's size, as jobs/animate.py)")
    p.add_argument("--up", choices=("auto", *UP_AXES), default="auto", help="the inputs' up axis (default auto)")
    p.add_argument("--max-vertices", type=int, default=DEFAULT_MAX_VERTICES,
                   help=f"refuse meshes with more vertices (default {DEFAULT_MAX_VERTICES:,})")
    p.add_argument("--max-frames", type=int, default=10_000, help="refuse longer clips (default 10,000)")
    p.add_argument("--actors", type=int, default=1, help="inference actors, each with the model loaded (default 1)")
    p.add_argument("--experiment", default="aniformer", help="MLflow experiment")
    p.add_argument("--no-mlflow", action="store_true", help="do not log to MLflow")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p.parse_args(argv)


def pair_options(args: argparse.Namespace, target: str, clip: ClipSource, out: Path) -> AnimateOptions:
    """jobs/animate.py's options for one pair: what `animate.py` would be run with for it alone, read by its parser
    (so with its defaults)."""
    argv = ["--checkpoint", args.checkpoint, "--target", target, "--driving", clip.path, "--out", str(out),
            "--no-progress", *(["--animation", clip.animation] if clip.animation is not None else []),
            "--unit", args.unit, "--up", args.up, "--max-vertices", str(args.max_vertices),
            "--max-frames", str(args.max_frames)]
    argv += ["--rig", "--bone-names", args.bone_names] * args.rig + ["--force"] * args.force
    return options_from(AnimateOptions, animate.parse_args(argv))


@releases_locks
def main(argv: list[str]) -> None:
    args = parse_args(argv)
    for flag, value in (("--actors", args.actors), ("--max-vertices", args.max_vertices),
                        ("--max-frames", args.max_frames)):
        if value < 1:
            raise UserError(f"{flag} must be >= 1, got {value}")
    if args.bone_names != "anny" and not args.rig:
        raise UserError("--bone-names names the rig's joints: add --rig")
    targets, clips = find_library(args.targets, args.clips)
    out = Path(args.out).expanduser().resolve()
    from aniformer.checkpoint import model_from_checkpoint, resolve_pretrained  # torch: after the arguments
    from aniformer.skinned_transfer import REFERENCE as SKINNED
    from aniformer.skinned_transfer import skinned_model

    checkpoint = resolve_pretrained(args.checkpoint)
    protect_inputs(out, {"--targets": args.targets, "--clips": args.clips, "--checkpoint": checkpoint})
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory")
    lock_output(out)  # one job per output; a rerun resumes in it
    if checkpoint == SKINNED:
        (model, state), blob = skinned_model(), None
    else:
        with tempfile.TemporaryDirectory(prefix="aniformer-retarget-") as scratch:
            local = animate.local_checkpoint(checkpoint, Path(scratch))
            model, state = model_from_checkpoint(local)  # a bad checkpoint: one line before Ray starts
            blob = local.read_bytes()
    registers = getattr(model.config, "output", "absolute") != "absolute"
    state = {"config": state["config"], "epoch": state.get("epoch")}

    from tqdm import tqdm

    from aniformer.cli.exits import exit_on_sigterm
    from pipeline.cluster import connect
    from pipeline.console import quiet_ray
    from pipeline.retarget import Pair, pair_row, schedule

    rows, todo = {}, []
    for target, target_path in targets.items():
        for clip, source in clips.items():
            pair_out = out / target / clip
            if (pair_out / "animation.json").is_file():  # complete: a pair's folder appears whole or not at all
                rows[target, clip] = {"target": target, "clip": clip, **pair_row(pair_out, "ok")}
            else:
                todo.append(Pair(target, clip, pair_out, pair_options(args, target_path, source, pair_out)))
    print(f"retarget {len(targets)} targets x {len(clips)} clips into {out}: {len(rows)} pairs complete already, "
          f"{len(todo)} to do", flush=True)
    started = time.perf_counter()
    with tqdm(total=len(targets) * len(clips), initial=len(rows), unit="pair", desc="retarget",
              disable=args.no_progress, file=sys.stderr) as bar:
        def say(line: str) -> None:  # above the bar, and at once (stdout is a pipe under ray job submit)
            bar.write(line, file=sys.stdout)
            sys.stdout.flush()

        for row in rows.values():
            say(pair_line(row))
        if todo:
            quiet_ray()
            connect()
            exit_on_sigterm()  # after ray.init, which installs its own handler
            options = {"up": args.up, "unit": args.unit, "max_vertices": args.max_vertices,
                       "max_frames": args.max_frames}
            for pair, row in schedule(todo, targets, clips, options, blob, state, registers, args.actors, say):
                row = {"target": pair.target, "clip": pair.clip, **row}
                if row["status"] == "error":
                    row["self_check"] = row.pop("error")
                rows[pair.target, pair.clip] = row
                say(pair_line(row))
                bar.update(1)
    seconds = time.perf_counter() - started
    ordered = [rows[target, clip] for target in targets for clip in clips]
    write_summary(out / "summary.csv", ordered)
    failed = [row for row in ordered if row["status"] != "ok"]
    print(f"retargeted {len(todo)} pairs in {seconds:.1f} s ({len(todo) / seconds if seconds else 0:.2f} pairs/s); "
          f"{len(ordered) - len(failed)} of {len(ordered)} ok")
    print(f"summary: {out / 'summary.csv'}")
    if not args.no_mlflow:
        from pipeline.tracking import tracking_uri

        params = {name: getattr(args, name) for name in ("targets", "clips", "checkpoint", "rig", "force", "actors")}
        print(f"MLflow run: {log_run(out, params, args.experiment, ordered, seconds, len(todo))} in {tracking_uri()}")
    if failed:
        raise UserError(f"{len(failed)} of {len(ordered)} pairs not written ("
                        + ", ".join(f"{row['target']} x {row['clip']}: {row['status']}" for row in failed[:3])
                        + (", ..." if len(failed) > 3 else "") + "); see summary.csv, rerun to retry them")


def cli() -> None:
    """The ``aniformer-retarget`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()

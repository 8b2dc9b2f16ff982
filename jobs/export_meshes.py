"""Export meshes as OBJ files: a driving sequence, a target and its ground truth, from a bank or a stream.

    python jobs/export_meshes.py --stream notoes_collapse3pc --split locomotion --out samples/walk
    python jobs/export_meshes.py --bank runs/bank/bank --split unseen --out samples/unseen
    python jobs/animate.py --checkpoint runs/default/best.pt --target samples/walk/target.obj \\
        --driving samples/walk/driving --out anim/walk

``--stream TOPOLOGY``: pair ``--pair`` of a split of the on-the-fly test stream
(``aniformer.synth.stream.STREAM_SPLITS``) with a ``--frames``-long driving clip: fresh bodies, never
trained on, the motion and orientation of the split, at a nominal 30 fps (``driving/sequence.json``).
``--bank DIR``: from split SPLIT of the bank (see `pipeline.data.BANK_SPLITS`): motion instance `--motion` (the split's
first by default) as performed by its driver -> `OUT/driving/frame_NNNN.obj`; target identity
`--target` (the split's first by default) at the first frame of another motion -> `OUT/target.obj`;
that target performing the same motion -> `OUT/ground_truth/frame_NNNN.obj` (what a perfect
animation gives). Uncentred, in the bank's metres, z up. Written to a temporary directory and
renamed into place; an existing non-empty OUT is refused unless `--overwrite`, and so is an OUT that is,
holds or lies inside the bank.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from aniformer.cli.args import ArgumentParser
from aniformer.cli.exits import run
from aniformer.cli.locks import releases_locks
from aniformer.cli.outputs import claim_output, staged_output_dir
from aniformer.errors import UserError


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = ArgumentParser(prog="export_meshes.py", description=__doc__.split("\n\n")[0],
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--bank", metavar="DIR", help="a mesh bank (OUT/bank of a training job)")
    source.add_argument("--stream", metavar="TOPOLOGY", help="pairs made on the fly on this Anny topology")
    p.add_argument("--split", help="split to take the motion and target from (default: unseen; locomotion for --stream)")
    p.add_argument("--pair", type=int, default=0, help="--stream: pair index (default: 0)")
    p.add_argument("--frames", type=int, default=30, help="--stream: frames of the driving clip (default: 30)")
    p.add_argument("--seed", type=int, default=0, help="--stream: the stream's seed (default: 0, as the configs)")
    p.add_argument("--motion", type=int, help="motion instance id (default: the split's first)")
    p.add_argument("--target", type=int, help="target identity id (default: the split's first)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--overwrite", action="store_true", help="replace an existing non-empty --out")
    return p.parse_args(argv)


def _pick(name: str, value: int | None, allowed: list[int], split: str) -> int:
    if value is None:
        return allowed[0]
    if value not in allowed:
        raise UserError(f"--{name} {value} is not in split {split!r} (it has {', '.join(map(str, allowed))})")
    return value


@releases_locks  # the --out lock ends with main, however main is called
def main(argv: list[str]) -> None:
    args = parse_args(argv)
    out = Path(args.out).expanduser().resolve()
    claim_output(out, args.overwrite, {"--bank": args.bank})  # one job per --out; --overwrite never deletes the bank
    (_export_stream if args.stream else _export_bank)(args, out)


def _write(out: Path, overwrite: bool, driving, truth, target, faces, info: dict) -> None:
    from aniformer.io.mesh import write_obj

    with staged_output_dir(out, overwrite) as tmp:
        for directory, frames in (("driving", driving), ("ground_truth", truth)):
            (tmp / directory).mkdir()
            for k, vertices in enumerate(frames):
                write_obj(tmp / directory / f"frame_{k:04d}.obj", vertices, faces)
        write_obj(tmp / "target.obj", target, faces)
        (tmp / "export.json").write_text(json.dumps(info, indent=2) + "\n")
        if "fps" in info:  # where jobs/animate.py reads the driver's frame rate
            (tmp / "driving" / "sequence.json").write_text(json.dumps({"fps": info["fps"]}) + "\n")
    print(f"driving: {out / 'driving'}  target: {out / 'target.obj'}  ground truth: {out / 'ground_truth'}")


def _export_stream(args, out: Path) -> None:
    from aniformer.synth.bodies import TOPOLOGIES
    from pipeline.data import DataConfig, pair_source

    split = args.split or "locomotion"
    if args.stream not in TOPOLOGIES:
        raise UserError(f"--stream must be one of {', '.join(TOPOLOGIES)}; got {args.stream!r}")
    source = pair_source(DataConfig(source="stream", topology=args.stream, shuffle="none"), None)
    if split not in source.splits:
        raise UserError(f"--split {split!r}: not a split of the stream ({', '.join(source.splits)})")
    if not 2 <= args.frames <= 1000 or args.pair < 0:
        raise UserError(f"--frames must be in [2, 1000] and --pair >= 0; got {args.frames} and {args.pair}")
    stream = source.with_settings(window=args.frames, center="none", seed=args.seed)  # a clip, uncentred
    pair = stream.batch(split, 0, [args.pair])
    info = {"stream": args.stream, "split": split, "description": stream.splits[split], "pair": args.pair,
            "seed": args.seed, "frames": args.frames, "vertices": stream.num_vertices, "fps": 30}
    _write(out, args.overwrite, pair["driving"][0], pair["ground_truth"][0], pair["target"][0], stream.faces, info)
    print(f"exported pair {args.pair} of the stream's {split!r} split ({args.frames} frames, "
          f"{stream.num_vertices} vertices)")


def _export_bank(args, out: Path) -> None:
    from pipeline.data import load_bank

    args.split = args.split or "unseen"
    bank_dir = Path(args.bank).expanduser().resolve()
    bank = load_bank(bank_dir)
    if args.split not in bank.non_empty_splits:
        raise UserError(f"--split {args.split!r}: not a non-empty split of the bank ({', '.join(bank.non_empty_splits)})")
    split = bank.manifest.splits[args.split]
    motion = _pick("motion", args.motion, split["motions"], args.split)
    target = _pick("target", args.target, split["targets"], args.split)
    info = bank.manifest.motions[motion]
    driving = bank.sequence(info["driver"], motion)
    truth = bank.sequence(target, motion)
    rest_motion = next(m["id"] for m in bank.manifest.motions if m["id"] != motion)
    target_mesh = bank.sequence(target, rest_motion)[0]
    driver_name, target_name = (bank.manifest.identities[i]["name"] for i in (info["driver"], target))
    print(f"exported {info['name']} ({len(driving)} frames, {bank.num_vertices} vertices) by {driver_name}, "
          f"target {target_name}")
    _write(out, args.overwrite, driving, truth, target_mesh, bank.faces, {
        "bank": str(bank_dir), "split": args.split, "motion": info, "driver": driver_name, "target": target_name,
        "target_pose_from_motion": rest_motion, "frames": len(driving), "vertices": bank.num_vertices})


def cli() -> None:
    """The ``aniformer-export-meshes`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()

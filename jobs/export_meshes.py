"""Export meshes from a mesh bank as OBJ files: a driving sequence, a target and its ground truth.

    python jobs/export_meshes.py --bank runs/default/bank --split unseen --out samples/unseen
    python jobs/animate.py --checkpoint runs/default/best.pt --target samples/unseen/target.obj \\
        --driving samples/unseen/driving --out anim/unseen

From split SPLIT of the bank (see `pipeline.data.SPLITS`): motion instance `--motion` (the split's
first by default) as performed by its driver -> `OUT/driving/frame_NNNN.obj`; target identity
`--target` (the split's first by default) at the first frame of another motion -> `OUT/target.obj`;
that target performing the same motion -> `OUT/ground_truth/frame_NNNN.obj` (what a perfect
animation gives). Uncentred, in the bank's metres, z up. Written to a temporary directory and
renamed into place; an existing non-empty OUT is refused unless `--overwrite`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script from a checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from aniformer.cli import ArgumentParser, UserError, check_output_dir, run, staged_output_dir  # noqa: E402


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = ArgumentParser(prog="export_meshes.py", description=__doc__.split("\n\n")[0],
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--bank", required=True, metavar="DIR", help="a mesh bank (OUT/bank of a training job)")
    p.add_argument("--split", default="unseen", help="split to take the motion and target from (default: unseen)")
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


def main(argv: list[str]) -> None:
    args = parse_args(argv)
    out = Path(args.out).expanduser().resolve()
    check_output_dir(out, args.overwrite)
    from aniformer.animate import write_obj
    from pipeline.data import load_bank

    bank_dir = Path(args.bank).expanduser().resolve()
    bank = load_bank(bank_dir)
    splits = bank.manifest["splits"]
    if args.split not in splits or not splits[args.split]["motions"] or not splits[args.split]["targets"]:
        raise UserError(f"--split {args.split!r}: not a non-empty split of the bank "
                        f"({', '.join(s for s in splits if splits[s]['motions'] and splits[s]['targets'])})")
    split = splits[args.split]
    motion = _pick("motion", args.motion, split["motions"], args.split)
    target = _pick("target", args.target, split["targets"], args.split)
    info = bank.manifest["motions"][motion]
    driving = bank.sequence(info["driver"], motion)
    truth = bank.sequence(target, motion)
    rest_motion = next(m["id"] for m in bank.manifest["motions"] if m["id"] != motion)
    target_mesh = bank.sequence(target, rest_motion)[0]
    driver_name, target_name = (bank.manifest["identities"][i]["name"] for i in (info["driver"], target))

    with staged_output_dir(out, args.overwrite) as tmp:
        for directory, frames in (("driving", driving), ("ground_truth", truth)):
            (tmp / directory).mkdir()
            for k, vertices in enumerate(frames):
                write_obj(tmp / directory / f"frame_{k:04d}.obj", vertices, bank.faces)
        write_obj(tmp / "target.obj", target_mesh, bank.faces)
        (tmp / "export.json").write_text(json.dumps({
            "bank": str(bank_dir), "split": args.split, "motion": info,
            "driver": driver_name, "target": target_name, "target_pose_from_motion": rest_motion,
            "frames": len(driving), "vertices": bank.num_vertices}, indent=2) + "\n")
    print(f"exported {info['name']} ({len(driving)} frames, {bank.num_vertices} vertices) by {driver_name}, "
          f"target {target_name}")
    print(f"driving: {out / 'driving'}  target: {out / 'target.obj'}  ground truth: {out / 'ground_truth'}")


if __name__ == "__main__":
    run(main)

"""Evaluate a checkpoint against the baselines: PMD (x1e-4) per split of a mesh bank, like the paper's Table 2.

    python jobs/evaluate.py --checkpoint runs/tiny/best.pt --out eval/tiny
    python jobs/evaluate.py --checkpoint 3f2a...c9 --bank data/default --out eval/default \\
        --compare npt=runs/npt/best.pt --compare regression=runs/head/best.pt --noise 0,0.005,0.01,0.02

``--checkpoint`` (and each ``--compare NAME=CKPT``) is a checkpoint file, an MLflow run id (its
``checkpoints/best.pt`` artifact) or a registered model (``models:/aniformer/latest``). A checkpoint
trained on a stream (``data.source: stream``) is
scored on the stream's splits, made on the fly (``--topology`` to score on another Anny topology);
otherwise the bank is ``--bank DIR``, else ``bank/`` beside the checkpoint (where jobs/train.py
puts it). Rows: the checkpoint, every ``--compare`` model and the baselines: copy-driver, the static
target (the target, unmoved) and the deformation transfer alone (aniformer/transfer.py), and with
``--skinned-transfer`` Anny's skeleton fitted to the driver and played on the target; columns:
every split (``--splits`` to choose). ``--noise`` adds a sweep of uniform driver noise on one split
(``--noise-split``) and plots PMD vs noise. Outputs in ``--out``: results.md, results.csv,
results.json (+ noise.csv, noise.png), written under a temporary name and renamed into place when
complete; they and the metrics are logged to the MLflow run
``evaluate-NAME`` (experiment ``aniformer``) unless ``--no-mlflow``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from aniformer.cli.args import ArgumentParser, options_from, resolve_device
from aniformer.cli.exits import run
from aniformer.cli.locks import releases_locks
from aniformer.cli.outputs import claim_output
from pipeline.evaluation import EvaluateOptions, check_flags, evaluate_checkpoint, refusals_line


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = ArgumentParser(prog="evaluate.py", description=__doc__.split("\n\n")[0],
                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--checkpoint", required=True, metavar="CKPT",
                   help="checkpoint file, MLflow run id, registered model (models:/aniformer/latest), "
                        "or pretrained (the shipped model, aniformer/weights/aniformer.pt)")
    p.add_argument("--out", required=True, metavar="DIR", help="directory for the tables and plots")
    p.add_argument("--bank", metavar="DIR", help="mesh bank (default: bank/ beside the checkpoint; none for a stream)")
    p.add_argument("--topology", help="stream checkpoints: the Anny topology of the pairs (default: the training one)")
    p.add_argument("--targets", metavar="VARIANTS",
                   help="stream checkpoints: score targets (and drivers) of other topologies instead of the splits, "
                        "e.g. same,remeshed,posed,rotated,lying,glb,seams,parts,dense,foreign_driver "
                        "(aniformer/synth/variants.py), on --target-split")
    p.add_argument("--target-split", default="characters", help="the split of --targets (default: characters)")
    p.add_argument("--compare", action="append", default=[], metavar="NAME=CKPT",
                   help="a baseline checkpoint (file or run id) as row NAME; repeatable")
    p.add_argument("--name", help="row label of --checkpoint and MLflow run evaluate-NAME (default: from the path)")
    p.add_argument("--pairs", type=int, help="pairs per split (default: the checkpoint's data.eval_pairs)")
    p.add_argument("--splits", help="comma-separated splits (default: every split of the bank)")
    p.add_argument("--noise", metavar="LEVELS", help="noise sweep: comma-separated amplitudes in metres, e.g. 0,0.005,0.01")
    p.add_argument("--noise-split", metavar="SPLIT", help="split of the noise sweep (default: unseen)")
    p.add_argument("--clip-frames", type=int, metavar="N",
                   help="stream checkpoints: also animate clips of N frames, window sliding as in animate.py, and "
                        "report the acceleration error (jitter) beside PMD (default 16; 0 for none)")
    p.add_argument("--clip-pairs", type=int, metavar="N",
                   help="clips per split for the acceleration error (default: --pairs, at most 64)")
    p.add_argument("--seed", type=int, help="pair seed (default: the checkpoint's data.seed, as in training)")
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--no-copy-driver", action="store_true",
                   help="leave out the baseline rows (copy-driver, static target, deformation transfer)")
    p.add_argument("--skinned-transfer", action="store_true",
                   help="also score the skinned transfer: Anny's skeleton fitted to every driving frame and played on "
                        "the target's fitted body (aniformer/skinned_transfer.py; no learning; ~4 s per pair on 2 "
                        "cores beside another job; pairs on Anny's topologies; not in the acceleration table)")
    p.add_argument("--device", default="auto", help="cpu, cuda, cuda:1 ... (default: cuda if available)")
    p.add_argument("--experiment", default="aniformer", help="MLflow experiment")
    p.add_argument("--no-mlflow", action="store_true", help="do not log to MLflow")
    p.add_argument("--overwrite", action="store_true", help="replace an existing non-empty --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p.parse_args(argv)


@releases_locks
def main(argv: list[str]) -> None:
    args = parse_args(argv)
    options = options_from(EvaluateOptions, args)
    levels, compare = check_flags(options)
    out = Path(args.out).expanduser().resolve()
    from aniformer.checkpoint import resolve_pretrained  # torch: after the arguments are checked

    checkpoint = resolve_pretrained(args.checkpoint)
    compare = [(label, resolve_pretrained(reference)) for label, reference in compare]
    claim_output(out, args.overwrite, {"--checkpoint": checkpoint, "--compare": [reference for _, reference in compare],
                                       "--bank": args.bank or Path(checkpoint).expanduser().parent / "bank"})
    device = resolve_device(args.device)
    evaluation = evaluate_checkpoint(options, checkpoint, compare, levels, out, device)
    print(evaluation.markdown.split("\n\n- ")[0].strip())
    if evaluation.refused is not None:
        print(refusals_line(evaluation.refused))
    print(f"evaluated {evaluation.models} models x {len(evaluation.splits)} splits x {evaluation.pairs} pairs "
          f"in {evaluation.seconds:.1f} s")
    print(f"results: {out / 'results.md'}, {out / 'results.csv'}" + (f", {out / 'noise.png'}" if evaluation.noise else ""))
    if evaluation.run_id:
        from pipeline.tracking import tracking_uri

        print(f"MLflow run: {evaluation.run_id} (evaluate-{evaluation.name}) in {tracking_uri()}")


def cli() -> None:
    """The ``aniformer-evaluate`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()

"""Ablation: train every variant of a config with the same budget, then one PMD table (the paper's Table 1).

    python jobs/ablate.py --config configs/ablation.yaml --out runs/ablation [train.epochs=4 ...]

The config is a run config plus an `ablation:` section naming the variants (see pipeline/ablation.py).
Each variant trains exactly as jobs/train.py does (Ray Train, checkpoints, MLflow) into
`OUT/runs/<variant>/`, all on one mesh bank (`--bank DIR`, else `OUT/bank`, generated on first use).
The table goes to `OUT/ablation.md`, `.csv` and `.json` and to the MLflow run of the ablation, whose
children are the variants' training runs. Running the same command again keeps the variants that
finished (their `best.pt`), resumes an interrupted one from its last checkpoint and trains the rest.
Without RAY_ADDRESS a local Ray instance is started.
"""

from __future__ import annotations

import json
import time

from aniformer.cli.args import RunJobParser
from aniformer.cli.exits import exit_on_sigterm, run
from aniformer.cli.locks import releases_locks
from aniformer.errors import UserError


@releases_locks  # the --out lock ends with main, however main is called
def main(argv: list[str]) -> None:
    args = RunJobParser("ablate.py", __doc__, out_help="output directory (runs/, ablation.md/.csv/.json)",
                        name_help="ablation name: MLflow parent run and job prefix").parse_args(argv)
    from pipeline.ablation import load_ablation_config, variant_specs

    base, ablation = load_ablation_config(args.config, args.overrides)
    specs = variant_specs(base, ablation)  # bad config or variant: one line before anything starts
    if len({(spec.data.center, spec.data.source, spec.data.topology) for spec in specs.values()}) > 1:
        raise UserError("ablation variants must share data.source, data.topology and data.center "
                        "(they are scored on the same pairs)")
    out, name, bank = RunJobParser.locations(args)

    from aniformer.evaluate import DEFAULT_CLIP_FRAMES
    from aniformer.io.files import atomic_path
    from aniformer.io.report import table_csv, table_markdown
    from pipeline.ablation import evaluate_variants, log_pmd_table, slug, train_variants, variant_notes
    from pipeline.cluster import connect
    from pipeline.console import quiet_ray
    from pipeline.data import prepare_bank
    from pipeline.tracking import quiet_mlflow, start_job_run, ui_hint

    quiet_mlflow()
    quiet_ray()
    connect()
    exit_on_sigterm()  # after ray.init, which installs its own handler
    first = next(iter(specs.values()))
    _, faces = prepare_bank(first.data, bank, generate=args.bank is None)
    variants = {slug(row): " ".join(overrides) or "(base)" for row, overrides in ablation.variants.items()}
    parent = start_job_run(name, {**first.to_dict(), "ablation": {**variants, "common": " ".join(ablation.common)}},
                           experiment=args.experiment, out=out)
    parent.set_tags({"kind": "ablation"})
    started = time.perf_counter()
    with parent.ended():
        checkpoints = train_variants(specs, bank, out, name, args.experiment, parent.run_id, faces)
        seed, pairs = first.data.seed, ablation.pairs or first.data.eval_pairs
        print(f"evaluating {len(specs)} variants on {pairs} pairs per split ...", flush=True)
        table, splits, acceleration = evaluate_variants(specs, checkpoints, bank, ablation, seed, pairs)
        markdown = table_markdown(table, splits, notes=variant_notes(specs, ablation, pairs, seed), ratios=True)
        if acceleration is not None:
            markdown += "\n" + table_markdown(acceleration, splits, ratios=True, title=(
                f"Acceleration error (mm/frame², lower is better): clips of {DEFAULT_CLIP_FRAMES} frames, each "
                "window sliding over the clip as in animate.py"))
        result = {"name": name, "bank": str(bank), "pairs": pairs, "seed": seed, "splits": splits, "table": table,
                  "acceleration": acceleration,
                  "variants": {row: {"overrides": list(ablation.variants[row]), "checkpoint": str(checkpoints[row]),
                                     "config": specs[row].to_dict()} for row in specs}}
        files = {"ablation.md": markdown, "ablation.csv": table_csv(table, splits),
                 "ablation.json": json.dumps(result, indent=2) + "\n"}
        for filename, text in files.items():
            with atomic_path(out / filename) as tmp:
                tmp.write_text(text)
            parent.log_artifact(out / filename, "ablation")
        log_pmd_table(parent, table, splits, notes={row: " ".join(ablation.variants[row]) or "(base config)" for row in specs})
        parent.log_metrics({f"pmd_{split}.{slug(row)}": value for row, values in table.items()
                            for split, value in values.items()}
                           | {f"accel_{split}.{slug(row)}": value for row, values in (acceleration or {}).items()
                              for split, value in values.items()}, step=0)
    print(markdown.split("\n\nEvery variant")[0].strip())
    print(f"ablation {name}: {len(specs)} variants in {time.perf_counter() - started:.0f} s")
    print(f"table: {out / 'ablation.md'}, {out / 'ablation.csv'}")
    print(f"MLflow run: {parent.run_id} in {parent.uri}")
    print(f"  compare the variants: {ui_hint(parent.uri)}")


def cli() -> None:
    """The ``aniformer-ablate`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()

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
from pathlib import Path

from aniformer.cli.args import RunJobParser
from aniformer.cli.exits import exit_on_sigterm, run
from aniformer.cli.locks import releases_locks
from aniformer.errors import UserError


def _train_variants(specs: dict, bank: Path, out: Path, name: str, experiment: str, parent_run_id: str,
                    faces) -> dict[str, Path]:
    """Train each variant that has no finished checkpoint yet; {row name: best.pt}."""
    from aniformer.checkpoint import load_checkpoint
    from pipeline.ablation import slug
    from pipeline.console import Console
    from pipeline.tracking import start_job_run
    from pipeline.trainer import train_job

    best = {}
    for row, spec in specs.items():
        run_dir = out / "runs" / slug(row)
        best[row] = run_dir / "best.pt"
        if best[row].is_file():
            if load_checkpoint(best[row])["config"] != spec.to_dict():
                raise UserError(f"{run_dir} holds a run of another config than variant {row!r}; "
                                "use a new --out (or remove that directory)")
            print(f"[{row}] kept: {best[row]}", flush=True)
            continue
        print(f"[{row}] training ({spec.model_name}, {spec.train.epochs} epochs) ...", flush=True)
        run_dir.mkdir(parents=True, exist_ok=True)
        tracker = start_job_run(f"{name}-{slug(row)}", spec.to_dict(), experiment=experiment,
                                parent_run_id=parent_run_id, out=run_dir)
        tracker.set_tags({"ablation.variant": row})
        with tracker.ended():
            result = train_job(spec, bank, run_dir, f"{name}-{slug(row)}", tracker, faces, Console.for_job())
        print(f"[{row}] PMD unseen {result.metrics.get('pmd_unseen', float('nan')):.3f} (x1e-4, validation)", flush=True)
    return best


def _evaluate(specs: dict, checkpoints: dict, bank_dir: Path, ablation, seed: int, pairs: int):
    """({row: {split: PMD x1e4}} on the same pairs for every row, the splits used, and on a stream
    {row: {split: acceleration error, mm/frame²}} on clips of ``DEFAULT_CLIP_FRAMES`` frames, else None)."""
    from aniformer.checkpoint import model_from_checkpoint
    from aniformer.evaluate import (
        DEFAULT_CLIP_FRAMES,
        DEFAULT_CLIP_PAIRS,
        Samplers,
        clip_accelerations,
        copy_driver_contender,
        evaluate_table,
        model_contender,
        static_target_contender,
        transfer_contender,
    )
    from pipeline.data import pair_source

    first = next(iter(specs.values())).data
    source = pair_source(first, bank_dir)
    splits = _scored_splits(source, ablation)

    def make_sampler(window: int, shuffle: str):
        return source.with_settings(window=window, shuffle=shuffle, seed=seed, eval_pairs=pairs)

    samplers = {}  # one per shuffle mode, each caching a sampler per window

    def sampler_for(shuffle: str) -> Samplers:
        if shuffle not in samplers:
            samplers[shuffle] = Samplers(make_sampler, shuffle)
        return samplers[shuffle]

    table, contenders = {}, []
    for row, spec in specs.items():
        model, _ = model_from_checkpoint(checkpoints[row])
        contenders.append(model_contender(row, model))
        table |= evaluate_table(contenders[-1:], sampler_for(spec.data.shuffle), splits, pairs=pairs, seed=seed)
    if ablation.copy_driver:
        baselines = [copy_driver_contender(first.window), static_target_contender(first.window),
                     transfer_contender(first.window)]
        contenders += baselines
        table |= evaluate_table(baselines, sampler_for("none"), splits, pairs=pairs, seed=seed)
    if first.source != "stream":
        return table, splits, None
    clips = make_sampler(DEFAULT_CLIP_FRAMES, "none")
    per_split = {split: clip_accelerations(contenders, clips, split, pairs=min(pairs, DEFAULT_CLIP_PAIRS))
                 for split in splits}
    return table, splits, {c.name: {split: float(per_split[split][c.name].mean()) for split in splits} for c in contenders}


def _scored_splits(source, ablation) -> list[str]:
    """``ablation.splits``, else every split of the data with pairs; `UserError` naming one it lacks."""
    available = source.non_empty_splits
    splits = list(ablation.splits) or available
    unknown = [s for s in splits if s not in available]
    if unknown:
        raise UserError(f"ablation.splits: unknown or empty split(s) {', '.join(unknown)}; the data has "
                        f"{', '.join(available)}")
    return splits


def _notes(specs: dict, ablation, pairs: int, seed: int) -> list[str]:
    """The lines under the table: how every variant was trained and scored, then each one's overrides."""
    from aniformer.memory import parameter_count

    first = next(iter(specs.values()))
    notes = [f"Every variant: {first.train.epochs} epochs x {first.data.pairs_per_epoch} pairs, batch "
             f"{first.train.batch_size}; scored on {pairs} pairs per split (seed {seed}) with the vertex "
             "shuffling it was trained with (the baselines: unshuffled). Variants (overrides of the base config"
             + (f", after `{' '.join(ablation.common)}` for every row" if ablation.common else "") + "):", ""]
    return notes + [f"- {row}: `{' '.join(ablation.variants[row]) or '(base config)'}` — "
                    f"{spec.model_name}, {parameter_count(spec.model):,} parameters, "
                    f"shuffle `{spec.data.shuffle}`" for row, spec in specs.items()]


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
    from pipeline.ablation import log_pmd_table, slug
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
        checkpoints = _train_variants(specs, bank, out, name, args.experiment, parent.run_id, faces)
        seed, pairs = first.data.seed, ablation.pairs or first.data.eval_pairs
        print(f"evaluating {len(specs)} variants on {pairs} pairs per split ...", flush=True)
        table, splits, acceleration = _evaluate(specs, checkpoints, bank, ablation, seed, pairs)
        markdown = table_markdown(table, splits, notes=_notes(specs, ablation, pairs, seed), ratios=True)
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

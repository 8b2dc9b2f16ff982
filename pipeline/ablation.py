"""Ablations like the paper's Table 1: variants of one run config, each trained with the same budget
through the training pipeline, then scored on the same pairs.

An ablation config is a run config (data/model/loss/train, as for jobs/train.py), or `base: FILE`
naming one (relative to the ablation config), plus::

    base: default.yaml            # the "full" row is then exactly that config
    ablation:
      pairs: 500                  # evaluation pairs per split (default: data.eval_pairs)
      splits: [seen, unseen]      # default: every split of the bank
      copy_driver: true           # add the baseline rows: copy-driver, static target, deformation transfer
      common: [model.temporal=embedding]   # overrides applied to every variant first
      variants:                   # row name -> key=value overrides of the base config (as on the CLI)
        regression head: [model.head=regression, loss.motion=0, loss.appearance=0]
        full: []

A variant may change anything but the budget: `train.epochs`, `train.batch_size` and
`data.pairs_per_epoch` stay the base config's. Every variant is evaluated on pairs drawn with the
same seed, with the vertex shuffling it was trained with (the copy-driver on unshuffled pairs).

`train_variants` trains every variant as jobs/train.py trains (keeping those that finished before),
`evaluate_variants` scores them all on the same pairs beside the baselines, `variant_notes` says how.

`log_pmd_table` logs such a table ({row: {split: PMD}}, the ablation's or jobs/evaluate.py's) into an
MLflow run as an MLflow table: the run's Artifacts tab shows it as a table, `mlflow.load_table` reads it
back, and the experiment's Evaluation view lines up the tables of several runs.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from aniformer.cli.args import apply_overrides, load_config
from aniformer.config import Section, from_dict
from aniformer.errors import UserError

BUDGET = (("train", "epochs"), ("train", "batch_size"), ("data", "pairs_per_epoch"))


@dataclass(frozen=True)
class AblationConfig(Section):
    """The `ablation:` section."""

    variants: dict = field(default_factory=dict)
    common: tuple = ()  # key=value overrides of every variant, before its own
    pairs: int | None = None
    splits: tuple = ()
    copy_driver: bool = True

    def __post_init__(self):
        super().__post_init__()
        if not all(isinstance(o, str) for o in self.common):
            raise ValueError("common must be a list of 'key=value' strings")
        if not isinstance(self.variants, dict) or not self.variants:
            raise ValueError("variants must map row names to lists of key=value overrides")
        for name, overrides in self.variants.items():
            if not isinstance(overrides, (list, tuple)) or not all(isinstance(o, str) for o in overrides):
                raise ValueError(f"variant {name!r}: overrides must be a list of 'key=value' strings")
        slugs = [slug(name) for name in self.variants]
        if len(set(slugs)) != len(slugs) or not all(slugs):
            raise ValueError(f"variant names must differ in their letters and digits, got {list(self.variants)}")
        if self.pairs is not None and int(self.pairs) < 1:
            raise ValueError(f"pairs must be >= 1, got {self.pairs}")


def slug(name: str) -> str:
    """A variant's directory and MLflow job suffix: '+L_m' -> 'l_m'."""
    return re.sub(r"[^0-9a-z]+", "_", str(name).lower()).strip("_")


def load_ablation_config(path: str | os.PathLike, overrides: Sequence[str] = ()) -> tuple[dict, AblationConfig]:
    """(the base run config with `overrides` applied, the parsed `ablation:` section) of an ablation config."""
    config = load_config(path)
    base_file = config.pop("base", None)
    if base_file is not None:
        beside = sorted(set(config) - {"ablation"})
        if beside:
            raise UserError(f"{path}: `base: {base_file}` and run sections ({', '.join(beside)}) together; "
                            "put the changes in the variants or the base config")
        config |= load_config(Path(path).parent / str(base_file))
    config = apply_overrides(config, overrides)
    return config, from_dict(AblationConfig, config.pop("ablation", None), "ablation")


def variant_specs(base: dict, ablation: AblationConfig) -> dict:
    """{row name: RunSpec} of every variant; `UserError` naming the variant if one is invalid or
    changes the training budget."""
    from pipeline.run_spec import RunSpec

    reference = RunSpec.from_config(base)
    specs = {}
    for name, overrides in ablation.variants.items():
        try:
            spec = RunSpec.from_config(apply_overrides(base, [*ablation.common, *overrides]))
        except UserError as e:
            raise UserError(f"ablation variant {name!r}: {e}") from None
        for section, key in BUDGET:
            mine, theirs = getattr(getattr(spec, section), key), getattr(getattr(reference, section), key)
            if mine != theirs:
                raise UserError(f"ablation variant {name!r} changes the budget ({section}.{key}={mine}, "
                                f"base {theirs}); every variant trains with the base config's budget")
        specs[name] = spec
    return specs


PMD_TABLE = "pmd_table.json"


def log_pmd_table(tracker, table: Mapping[str, Mapping[str, float]], splits: Sequence[str],
                  artifact_file: str = f"ablation/{PMD_TABLE}", notes: Mapping[str, str] | None = None) -> str:
    """Log `table` ({row: {split: PMD x1e-4}}) into the run of `tracker` as an MLflow table at
    `artifact_file` (a `.json` path): columns `method`, one per split, and `notes` (e.g. a variant's
    overrides) as a last `about` column when given. Written as `mlflow.log_table` writes one (pandas
    "split" JSON, listed in the run's `mlflow.loggedArtifacts` tag), but replaced, not appended to, when
    the same run logs it again (a resumed job). Returns `artifact_file`."""
    import pandas as pd
    from mlflow.utils.mlflow_tags import MLFLOW_LOGGED_ARTIFACTS

    if not artifact_file.endswith(".json"):
        raise ValueError(f"artifact_file must end in .json, got {artifact_file!r}")
    rows = [{"method": row, **{split: float(values[split]) for split in splits},
             **({"about": notes.get(row, "")} if notes else {})} for row, values in table.items()]
    frame = pd.DataFrame(rows, columns=["method", *splits, *(["about"] if notes else [])])
    directory, _, name = artifact_file.rpartition("/")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        frame.to_json(path, orient="split", index=False)
        tracker.log_artifact(path, directory or None)
    logged = json.loads(tracker.client.get_run(tracker.run_id).data.tags.get(MLFLOW_LOGGED_ARTIFACTS, "[]"))
    entry = {"path": artifact_file, "type": "table"}
    if entry not in logged:
        tracker.set_tags({MLFLOW_LOGGED_ARTIFACTS: json.dumps([*logged, entry])})
    return artifact_file


def train_variants(specs: dict, bank: Path, out: Path, name: str, experiment: str, parent_run_id: str,
                    faces) -> dict[str, Path]:
    """Train each variant that has no finished checkpoint yet; {row name: best.pt}."""
    from aniformer.checkpoint import load_checkpoint
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


def evaluate_variants(specs: dict, checkpoints: dict, bank_dir: Path, ablation, seed: int, pairs: int):
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
    splits = scored_splits(source, ablation)

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


def scored_splits(source, ablation) -> list[str]:
    """``ablation.splits``, else every split of the data with pairs; `UserError` naming one it lacks."""
    available = source.non_empty_splits
    splits = list(ablation.splits) or available
    unknown = [s for s in splits if s not in available]
    if unknown:
        raise UserError(f"ablation.splits: unknown or empty split(s) {', '.join(unknown)}; the data has "
                        f"{', '.join(available)}")
    return splits


def variant_notes(specs: dict, ablation, pairs: int, seed: int) -> list[str]:
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

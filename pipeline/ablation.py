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

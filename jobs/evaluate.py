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
target (the target, unmoved) and the deformation transfer alone (aniformer/transfer.py); columns:
every split (``--splits`` to choose). ``--noise`` adds a sweep of uniform driver noise on one split
(``--noise-split``) and plots PMD vs noise. Outputs in ``--out``: results.md, results.csv,
results.json (+ noise.csv, noise.png), written under a temporary name and renamed into place when
complete; they and the metrics are logged to the MLflow run
``evaluate-NAME`` (experiment ``aniformer``) unless ``--no-mlflow``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

from aniformer.cli import ArgumentParser, resolve_device, run
from aniformer.errors import UserError
from aniformer.files import claim_output, releases_locks, staged_output_dir
from pipeline.registry import resolve_checkpoint
from pipeline.tracking import RUN_ID, quiet_mlflow

if TYPE_CHECKING:
    from collections.abc import Sequence

    from pipeline.data import DataConfig, PairSource


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
                        "e.g. same,remeshed,posed,rotated,lying,glb,parts,dense,foreign_driver "
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
    p.add_argument("--device", default="auto", help="cpu, cuda, cuda:1 ... (default: cuda if available)")
    p.add_argument("--experiment", default="aniformer", help="MLflow experiment")
    p.add_argument("--no-mlflow", action="store_true", help="do not log to MLflow")
    p.add_argument("--overwrite", action="store_true", help="replace an existing non-empty --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p.parse_args(argv)


def _model_label(state: dict, model) -> str:
    name = state["config"].get("model", {}).get("name", "aniformer")
    if name == "npt":
        return "NPT"
    return "regression head" if model.config.head == "regression" else "AniFormer"


def _default_name(reference: str) -> str:
    if reference.startswith("models:/"):  # a registered model: models:/aniformer/3 -> aniformer-3
        return re.sub(r"[/@]", "-", reference.removeprefix("models:/").rstrip("/"))
    match = RUN_ID.fullmatch(reference)
    if match and not Path(reference).exists():
        return match.group(1)[:8]
    path = Path(reference).resolve()
    return (path.parent.name if path.is_file() else path.name) or "checkpoint"


def check_flags(args: argparse.Namespace) -> tuple[list[float] | None, list[tuple[str, str]]]:
    """(noise levels, --compare NAME=CKPT pairs) from the flags, checked before anything is loaded."""
    if args.pairs is not None and args.pairs < 1:
        raise UserError(f"--pairs must be >= 1, got {args.pairs}")
    if args.batch_size < 1:
        raise UserError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.clip_pairs is not None and args.clip_pairs < 1:
        raise UserError(f"--clip-pairs must be >= 1, got {args.clip_pairs}")
    if args.clip_frames is not None and args.clip_frames != 0 and args.clip_frames < 3:
        raise UserError(f"--clip-frames must be 0 (none) or >= 3 (an acceleration needs three frames), got {args.clip_frames}")
    from aniformer.evaluate import parse_levels

    try:
        levels = parse_levels(args.noise) if args.noise is not None else None
    except ValueError as e:
        raise UserError(f"--noise: {e}") from None
    compare = []
    for item in args.compare:
        label, sep, reference = item.partition("=")
        if not sep or not label.strip() or not reference:
            raise UserError(f"--compare {item!r} is not of the form NAME=CKPT")
        compare.append((label.strip(), reference))
    return levels, compare


@dataclasses.dataclass(frozen=True)
class EvalData:
    """What a checkpoint is scored on (`choose_data`); read by field name only."""

    source: PairSource  # the checkpoint's stream, or a bank, with the checkpoint's pair settings
    pairs: int  # per split
    seed: int
    label: str  # the data, as the notes and results.json name it
    columns: dict[str, str]  # what can be scored, name -> description: splits with pairs, or --targets' variants
    notes: Sequence[str] = ()  # lines under the table
    clip_frames: int = 0  # the acceleration error's clip length (a stream's splits only); 0: none
    splits: Sequence[str] = ()  # the columns scored (--splits)
    noise_split: str = ""  # the split of the noise sweep

    def sampler(self, window: int, shuffle: str) -> PairSource:
        """The pairs a model of ``window`` is scored on: every model's are the same pairs, shuffled as ``shuffle`` says."""
        return self.source.with_settings(window=window, shuffle=shuffle, seed=self.seed, eval_pairs=self.pairs)


def choose_data(args: argparse.Namespace, ckpt_path: Path, config: dict, levels) -> EvalData:
    """What a checkpoint is scored on, from its run config and the flags: the target variants (--targets),
    its stream (a stream checkpoint without --bank), or a bank."""
    from pipeline.data import data_config

    cfg = data_config(config)
    pairs, seed = args.pairs or cfg.eval_pairs, cfg.seed if args.seed is None else args.seed
    if args.targets is not None:
        data = _target_data(args, cfg, pairs, seed)
    elif cfg.source == "stream" and not args.bank:
        data = _stream_data(args, cfg, pairs, seed)
    else:
        data = _bank_data(args, ckpt_path, cfg, pairs, seed)
    if args.clip_frames and not data.clip_frames:
        raise UserError("--clip-frames applies to the splits of a stream checkpoint (no --bank, no --targets)")
    return _with_splits(args, data, levels)


def _with_splits(args: argparse.Namespace, data: EvalData, levels) -> EvalData:
    """``data`` with the columns to score (--splits, else all) and the noise sweep's split."""
    columns = data.columns
    splits = [s.strip() for s in args.splits.split(",")] if args.splits else list(columns)
    unknown = [s for s in splits if s not in columns]
    if unknown or not splits:
        raise UserError(f"--splits: unknown split(s) {', '.join(unknown) or '(none given)'}; "
                        f"the data has {', '.join(columns)}")
    noise_split = args.noise_split or ("unseen" if "unseen" in splits else splits[-1])
    if levels is not None and noise_split not in columns:
        raise UserError(f"--noise-split {noise_split!r} is not a split of the data ({', '.join(columns)})")
    return dataclasses.replace(data, splits=splits, noise_split=noise_split)


def refusals_line(refused: dict[str, list[bool]]) -> str:
    """--targets: how many of each variant's model results the self-check refused, as one line."""
    counts = ", ".join(f"`{variant}` {sum(values)}/{len(values)}" for variant, values in refused.items())
    return f"Refused by the self-check (aniformer/trust.py), of the model's results: {counts}."


def results_report(args, state: dict, table: dict, spread: dict, sweep, levels, data: EvalData, *, seconds: float,
                   refused: dict[str, list[bool]] | None = None, accelerations: dict | None = None) -> tuple[str, dict]:
    """The results as Markdown (mean and SD tables with each model's ratios, the acceleration errors, the
    noise sweep, --targets' refusals) and as the results.json record."""
    from aniformer.evaluate import table_markdown

    splits, pairs, seed, noise_split, clip_frames = data.splits, data.pairs, data.seed, data.noise_split, data.clip_frames
    notes = [*data.notes, f"{pairs} pairs per split (seed {seed}, window as each model's, vertex shuffling "
                          f"'{data.source.shuffle}'; copy-driver on the same pairs unshuffled). Checkpoint: "
                          f"{args.checkpoint} (epoch {state.get('epoch')}); data: {data.label}."]
    markdown = table_markdown(table, splits, data.columns, notes=notes, ratios=True)
    markdown += "\n" + table_markdown(spread, splits, title="Standard deviation of PMD over the pairs of each split")
    acceleration = acceleration_sd = None
    if accelerations is not None:
        clips = len(next(iter(next(iter(accelerations.values())).values())))
        acceleration = {name: {s: float(v.mean()) for s, v in row.items()} for name, row in accelerations.items()}
        acceleration_sd = {name: {s: float(v.std(ddof=1)) if len(v) > 1 else float("nan") for s, v in row.items()}
                           for name, row in accelerations.items()}
        markdown += "\n" + table_markdown(
            acceleration, splits, ratios=True,
            title=f"Acceleration error (mm/frame², lower is better): {clips} clips of {clip_frames} frames per split, "
                  "each method's window sliding over the clip as in animate.py; predicted against true vertex accelerations")
        markdown += "\n" + table_markdown(acceleration_sd, splits, title="Standard deviation of the acceleration error")
    if refused is not None:
        markdown += "\n" + refusals_line(refused) + "\n"
    if sweep is not None:
        markdown += (f"\n**PMD (×10⁻⁴) vs uniform driver noise (± m), split `{noise_split}`**\n\n"
                     + table_markdown({k: {f"{lv:g}": v for lv, v in row.items()} for k, row in sweep.items()},
                                      [f"{lv:g}" for lv in levels], title=None)
                     + "\n![PMD vs noise](noise.png)\n")
    result = {"checkpoint": args.checkpoint, "data": data.label, "pairs": pairs, "seed": seed,
              "splits": splits, "table": table, "pair_sd": spread, "seconds": seconds,
              "noise": None if sweep is None else {"split": noise_split,
                                                   "pmd": {k: {f"{lv:g}": v for lv, v in row.items()}
                                                           for k, row in sweep.items()}}}
    if refused is not None:
        result["refused"] = {variant: [bool(r) for r in values] for variant, values in refused.items()}
    if acceleration is not None:
        result |= {"clip_frames": clip_frames, "clip_pairs": clips, "acceleration": acceleration,
                   "acceleration_sd": acceleration_sd}

    return markdown, result


def write_results(out: Path, args: argparse.Namespace, markdown: str, result: dict, table: dict, sweep, config: dict,
                  name: str) -> str | None:
    """results.md/.csv/.json (and the noise sweep's CSV and plot), staged, and the MLflow run; its id."""
    from aniformer.evaluate import plot_sweep, sweep_csv, table_csv

    splits, pairs, seed = result["splits"], result["pairs"], result["seed"]
    with staged_output_dir(out, args.overwrite) as tmp:
        (tmp / "results.md").write_text(markdown)
        (tmp / "results.csv").write_text(table_csv(table, splits))
        (tmp / "results.json").write_text(json.dumps(result, indent=2) + "\n")
        if sweep is not None:
            (tmp / "noise.csv").write_text(sweep_csv(sweep))
            plot_sweep(sweep, tmp / "noise.png", result["noise"]["split"])
        run_id = None
        if not args.no_mlflow:
            run_id = _log_to_mlflow(f"evaluate-{name}", args, tmp, table, sweep, pairs, seed, splits, config,
                                    result.get("acceleration"))

    return run_id


def load_models(checkpoint: str, compare: list) -> tuple[Path, object, dict, list]:
    """(the checkpoint's path, its model, its state, the --compare rows (label, model))."""
    from aniformer.checkpoint import model_from_checkpoint

    with tempfile.TemporaryDirectory(prefix="aniformer-eval-") as scratch:
        ckpt_path = resolve_checkpoint(checkpoint, Path(scratch))
        model, state = model_from_checkpoint(ckpt_path)
        others = [(label, model_from_checkpoint(resolve_checkpoint(reference, Path(scratch)))[0])
                  for label, reference in compare]
    return ckpt_path, model, state, others


def contenders_of(args, rows: list, window: int, device):
    """The rows' models, then (unless --no-copy-driver) the three baselines, under unique names."""
    from aniformer.evaluate import copy_driver_contender, model_contender, static_target_contender, transfer_contender

    baselines = ["copy-driver", "static target", "deformation transfer"]
    labels = [r[0] for r in rows] + ([] if args.no_copy_driver else baselines)
    if len(set(labels)) != len(labels):
        raise UserError(f"row names must be unique, got {', '.join(labels)}")
    contenders = [model_contender(label, m, device) for label, m in rows]
    if not args.no_copy_driver:  # one topology per bank or stream: driver and target always correspond
        contenders += [copy_driver_contender(window), static_target_contender(window), transfer_contender(window)]
    return contenders


def score(args, rows, contenders, data: EvalData, levels, device):
    """({row: {split: per-pair PMDs}}, the noise sweep or None, --targets: {variant: per pair, whether the
    self-check refused the model's result} or None, ``data.clip_frames``: {row: {split: per-clip acceleration
    errors}} or None), with a progress bar on stderr."""
    from tqdm import tqdm

    from aniformer.evaluate import DEFAULT_CLIP_PAIRS, Samplers, clip_accelerations, evaluate_pairs, noise_sweep, target_pmds

    model, splits, pairs, seed = rows[0][1], data.splits, data.pairs, data.seed
    if args.targets is not None:
        refused: dict[str, list[bool]] = {}
        with tqdm(total=pairs, unit="pair", desc="evaluate targets", disable=args.no_progress, file=sys.stderr) as bar:
            scores = target_pmds(model, data.sampler(model.config.window, "none"), args.target_split, splits,
                                 pairs=pairs, device=device, batch_size=args.batch_size, progress=lambda: bar.update(1),
                                 refused=refused)
        return {rows[0][0]: scores.pop("model"), **scores}, None, refused, None
    samplers = Samplers(data.sampler, data.source.shuffle)
    steps = len(contenders) * (len(splits) + (len(levels) if levels else 0)) + (len(splits) if data.clip_frames else 0)
    with tqdm(total=steps, unit="split", desc="evaluate", disable=args.no_progress, file=sys.stderr) as bar:
        scores = evaluate_pairs(contenders, samplers, splits, pairs=pairs, batch_size=args.batch_size, seed=seed,
                                progress=lambda *_: bar.update(1))
        sweep = None if levels is None else noise_sweep(contenders, samplers, data.noise_split, levels, pairs=pairs,
                                                        batch_size=args.batch_size, seed=seed,
                                                        progress=lambda *_: bar.update(1))
        accelerations = None
        if data.clip_frames:
            clips = data.sampler(data.clip_frames, "none")
            clip_pairs = args.clip_pairs or min(pairs, DEFAULT_CLIP_PAIRS)
            accelerations = {c.name: {} for c in contenders}
            for split in splits:
                for name, values in clip_accelerations(contenders, clips, split, pairs=clip_pairs).items():
                    accelerations[name][split] = values
                bar.update(1)
    return scores, sweep, None, accelerations


@releases_locks
def main(argv: list[str]) -> None:
    args = parse_args(argv)
    levels, compare = check_flags(args)
    out = Path(args.out).expanduser().resolve()
    from aniformer.checkpoint import resolve_pretrained  # torch: after the arguments are checked

    checkpoint = resolve_pretrained(args.checkpoint)
    compare = [(label, resolve_pretrained(reference)) for label, reference in compare]
    claim_output(out, args.overwrite, {"--checkpoint": checkpoint, "--compare": [reference for _, reference in compare],
                                       "--bank": args.bank or Path(checkpoint).expanduser().parent / "bank"})
    device = resolve_device(args.device)
    start = time.perf_counter()
    ckpt_path, model, state, others = load_models(checkpoint, compare)
    config = state["config"]
    data = choose_data(args, ckpt_path, config, levels)
    name = args.name or _default_name(args.checkpoint)
    rows = [(args.name or _model_label(state, model), model), *others]
    contenders = contenders_of(args, rows, model.config.window, device)
    scores, sweep, refused, accelerations = score(args, rows, contenders, data, levels, device)
    table = {name: {split: float(v.mean()) for split, v in row.items()} for name, row in scores.items()}
    spread = {name: {split: float(v.std(ddof=1)) if len(v) > 1 else float("nan") for split, v in row.items()}
              for name, row in scores.items()}
    seconds = time.perf_counter() - start

    markdown, result = results_report(args, state, table, spread, sweep, levels, data, seconds=seconds,
                                      refused=refused, accelerations=accelerations)
    result["per_pair"] = {name: {split: [round(float(x), 4) for x in v] for split, v in row.items()}
                          for name, row in scores.items()}  # the means' pairs, in pair order (as "refused")
    run_id = write_results(out, args, markdown, result, table, sweep, config, name)
    print(markdown.split("\n\n- ")[0].strip())
    if refused is not None:
        print(refusals_line(refused))
    print(f"evaluated {len(scores)} models x {len(data.splits)} splits x {data.pairs} pairs in {seconds:.1f} s")
    print(f"results: {out / 'results.md'}, {out / 'results.csv'}" + (f", {out / 'noise.png'}" if sweep else ""))
    if run_id:
        from pipeline.tracking import tracking_uri

        print(f"MLflow run: {run_id} (evaluate-{name}) in {tracking_uri()}")


def _columns(source: PairSource) -> dict[str, str]:
    """The splits pairs can be drawn from, name -> description."""
    return {s: source.splits[s] for s in source.non_empty_splits}


def _stream(args, cfg: DataConfig) -> PairSource:
    """The checkpoint's stream, on --topology if given."""
    from aniformer.synth.bodies import TOPOLOGIES
    from pipeline.data import pair_source

    topology = args.topology or cfg.topology
    if topology not in TOPOLOGIES:
        raise UserError(f"--topology must be one of {', '.join(TOPOLOGIES)}; got {topology!r}")
    return pair_source(dataclasses.replace(cfg, topology=topology), None)


def _stream_data(args, cfg: DataConfig, pairs: int, seed: int) -> EvalData:
    """The stream's splits, made on the fly, and the acceleration error's clips."""
    from aniformer.evaluate import DEFAULT_CLIP_FRAMES
    from aniformer.synth.poses import LIBRARY_FRAMES

    source = _stream(args, cfg)
    clip_frames = DEFAULT_CLIP_FRAMES if args.clip_frames is None else args.clip_frames
    if clip_frames > LIBRARY_FRAMES:
        raise UserError(f"--clip-frames must be at most {LIBRARY_FRAMES} (the stream's longest clip), got {clip_frames}")
    return EvalData(source, pairs, seed, f"stream, topology {source.topology}", _columns(source), clip_frames=clip_frames)


def _target_data(args, cfg: DataConfig, pairs: int, seed: int) -> EvalData:
    """``--targets``: variants of the targets of one stream split, as the columns."""
    from aniformer.synth.variants import DRIVER_FRAMES, VARIANTS

    if cfg.source != "stream" or args.bank or args.compare or args.noise:
        raise UserError("--targets scores a stream checkpoint alone: no --bank, --compare or --noise")
    source = _stream(args, cfg)
    if args.target_split not in source.splits:
        raise UserError(f"--target-split {args.target_split!r}: known splits are {', '.join(source.splits)}")
    variants = [v.strip() for v in args.targets.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or not variants:
        raise UserError(f"--targets: unknown variant(s) {', '.join(unknown) or '(none given)'}; known: {', '.join(VARIANTS)}")
    notes = [f"Targets of split `{args.target_split}` ({source.splits[args.target_split]}); the model and "
             "the deformation transfer reach targets of other topologies through aniformer/registration.py, "
             "the copy-driver is carried to the target's vertices through the ground-truth correspondence."]
    if "foreign_driver" in variants:
        notes.append(f"`foreign_driver`: the driver is registered on its whole {DRIVER_FRAMES}-frame clip "
                     "(aniformer/registration.py: register_clip), and the model slides its window over the clip "
                     "(aniformer/animate.py); every frame is scored.")
    return EvalData(source, pairs, seed, f"stream, topology {source.topology}", {v: VARIANTS[v] for v in variants}, notes)


def _bank_data(args, ckpt_path: Path, cfg: DataConfig, pairs: int, seed: int) -> EvalData:
    """The splits with pairs of a mesh bank: --bank, else bank/ beside the checkpoint."""
    from pipeline.data import load_bank, pair_source

    if args.topology:
        raise UserError("--topology applies to checkpoints trained on a stream (data.source: stream)")
    bank_dir = _bank_dir(args, ckpt_path)
    bank = load_bank(bank_dir)
    source = pair_source(dataclasses.replace(cfg, source="bank"), bank)  # a stream checkpoint too, given --bank
    named = [s.strip() for s in (args.splits or "").split(",")]
    empty = [s for s in named if s in source.splits and s not in source.non_empty_splits]
    if empty:
        raise UserError(f"--splits: split(s) {', '.join(empty)} are empty in this bank")
    return EvalData(source, pairs, seed, f"bank {bank_dir.resolve()}", _columns(source), _bank_notes(cfg, bank.manifest))


def _bank_dir(args, ckpt_path: Path) -> Path:
    """--bank, else bank/ beside the checkpoint file."""
    if args.bank:
        return Path(args.bank).expanduser()
    if not Path(os.path.expanduser(args.checkpoint)).exists():
        raise UserError("--checkpoint is an MLflow run id: pass --bank DIR (the mesh bank to evaluate on)")
    bank_dir = ckpt_path.parent / "bank" if ckpt_path.is_file() else ckpt_path / "bank"
    if not (bank_dir / "manifest.json").is_file():
        raise UserError(f"no mesh bank beside the checkpoint ({bank_dir}); pass --bank DIR")
    return bank_dir


def _bank_notes(cfg: DataConfig, manifest) -> list[str]:
    """A note (also on stderr) when a synthetic bank was made with other settings than the checkpoint's data."""
    from pipeline.data import GENERATION_FIELDS

    made, trained = manifest.config, cfg.generation_dict()
    differs = [k for k in GENERATION_FIELDS if k in made and made[k] != trained[k]]
    if manifest.kind != "synthetic" or not differs:
        return []
    note = (f"Note: the bank differs from the checkpoint's training data in {', '.join(differs)}; "
            "'seen' motions may not be the ones it was trained on.")
    print(note, file=sys.stderr)
    return [note]


def _log_to_mlflow(job: str, args, files: Path, table, sweep, pairs, seed, splits, config, acceleration=None) -> str:
    quiet_mlflow()
    from pipeline.tracking import start_job_run

    params = {"evaluate": {"checkpoint": args.checkpoint, "bank": str(args.bank or ""), "topology": args.topology or "",
                           "pairs": pairs, "seed": seed, "splits": splits, "clip_frames": args.clip_frames,
                           "clip_pairs": args.clip_pairs, "compare": args.compare, "noise": args.noise or ""}, **config}
    try:
        tracker = start_job_run(job, params, experiment=args.experiment, out=Path(args.out).expanduser().resolve())
        with tracker.ended():
            metrics = {f"pmd_{split}.{_metric_name(row)}": value
                       for row, values in table.items() for split, value in values.items()}
            metrics |= {f"accel_{split}.{_metric_name(row)}": value
                        for row, values in (acceleration or {}).items() for split, value in values.items()}
            tracker.log_metrics(metrics, step=0)
            from pipeline.ablation import log_pmd_table

            log_pmd_table(tracker, table, splits, artifact_file="evaluation/pmd_table.json")
            if sweep is not None:
                for i, level in enumerate(next(iter(sweep.values()))):
                    tracker.log_metrics({f"pmd_noise.{_metric_name(row)}": values[level] for row, values in sweep.items()}
                                        | {"noise_m": level}, step=i)
            for path in sorted(files.iterdir()):
                tracker.log_artifact(path, "evaluation")
            source = RUN_ID.fullmatch(args.checkpoint)
            if source and not Path(args.checkpoint).exists():
                tracker.set_tags({"aniformer.source_run": source.group(1)})
    except UserError:
        raise
    except Exception as e:  # unreachable server, bad URI ...
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise UserError(f"MLflow logging failed ({first[:200]}); rerun with --no-mlflow to skip it") from None
    return tracker.run_id


def _metric_name(label: str) -> str:
    return re.sub(r"[^0-9A-Za-z_\-.]+", "_", label)


def cli() -> None:
    """The ``aniformer-evaluate`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()

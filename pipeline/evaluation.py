"""One run of jobs/evaluate.py: its options (`EvaluateOptions`), the models loaded, every row scored on the
data `pipeline.evaluation_data.choose_data` picks, the results written and logged to MLflow (`evaluate_checkpoint`)."""

from __future__ import annotations

import json
import re
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from aniformer.cli.outputs import staged_output_dir
from aniformer.errors import UserError
from pipeline.evaluation_data import EvalData, choose_data


@dataclass(frozen=True)
class EvaluateOptions:
    """jobs/evaluate.py's flags as parsed, all but ``--out`` and ``--device`` (see its ``--help``)."""

    checkpoint: str
    bank: str | None
    topology: str | None
    targets: str | None
    target_split: str
    compare: list[str]
    name: str | None
    pairs: int | None
    splits: str | None
    noise: str | None
    noise_split: str | None
    clip_frames: int | None
    clip_pairs: int | None
    seed: int | None
    batch_size: int
    no_copy_driver: bool
    skinned_transfer: bool
    experiment: str
    no_mlflow: bool
    overwrite: bool
    no_progress: bool


@dataclass(frozen=True)
class Evaluation:
    """What `evaluate_checkpoint` did, for the job's summary lines."""

    markdown: str  # results.md
    refused: dict[str, list[bool]] | None  # --targets: per variant and pair, whether the self-check refused
    models: int  # rows scored
    splits: list[str]
    pairs: int  # per split
    seconds: float  # loading and scoring
    noise: bool  # whether noise.png was written
    name: str  # of the MLflow run evaluate-NAME
    run_id: str | None  # the MLflow run; None with --no-mlflow


def check_flags(options: EvaluateOptions) -> tuple[list[float] | None, list[tuple[str, str]]]:
    """(noise levels, --compare NAME=CKPT pairs) from the flags, checked before anything is loaded."""
    if options.pairs is not None and options.pairs < 1:
        raise UserError(f"--pairs must be >= 1, got {options.pairs}")
    if options.batch_size < 1:
        raise UserError(f"--batch-size must be >= 1, got {options.batch_size}")
    if options.clip_pairs is not None and options.clip_pairs < 1:
        raise UserError(f"--clip-pairs must be >= 1, got {options.clip_pairs}")
    if options.clip_frames is not None and options.clip_frames != 0 and options.clip_frames < 3:
        raise UserError(f"--clip-frames must be 0 (none) or >= 3 (an acceleration needs three frames), got {options.clip_frames}")
    from aniformer.evaluate import parse_levels

    try:
        levels = parse_levels(options.noise) if options.noise is not None else None
    except ValueError as e:
        raise UserError(f"--noise: {e}") from None
    compare = []
    for item in options.compare:
        label, sep, reference = item.partition("=")
        if not sep or not label.strip() or not reference:
            raise UserError(f"--compare {item!r} is not of the form NAME=CKPT")
        compare.append((label.strip(), reference))
    return levels, compare


def evaluate_checkpoint(options: EvaluateOptions, checkpoint: str, compare: list[tuple[str, str]], levels,
                        out: Path, device) -> Evaluation:
    """Score ``checkpoint`` (resolved by `resolve_pretrained`, as ``compare``'s references) and the baselines,
    write the results into ``out`` and log them to MLflow."""
    start = time.perf_counter()
    ckpt_path, model, state, others = load_models(checkpoint, compare)
    config = state["config"]
    data = choose_data(options, ckpt_path, config, levels)
    name = options.name or _default_name(options.checkpoint)
    rows = [(options.name or _model_label(state, model), model), *others]
    contenders = contenders_of(options, rows, model.config.window, device)
    scores, sweep, refused, accelerations = score(options, rows, contenders, data, levels, device)
    table = {name: {split: float(v.mean()) for split, v in row.items()} for name, row in scores.items()}
    spread = {name: {split: float(v.std(ddof=1)) if len(v) > 1 else float("nan") for split, v in row.items()}
              for name, row in scores.items()}
    seconds = time.perf_counter() - start

    markdown, result = results_report(options, state, table, spread, sweep, levels, data, seconds=seconds,
                                      refused=refused, accelerations=accelerations)
    result["per_pair"] = {name: {split: [round(float(x), 4) for x in v] for split, v in row.items()}
                          for name, row in scores.items()}  # the means' pairs, in pair order (as "refused")
    run_id = write_results(out, options, markdown, result, table, sweep, config, name)
    return Evaluation(markdown, refused, len(scores), list(data.splits), data.pairs, seconds, sweep is not None,
                      name, run_id)


def _model_label(state: dict, model) -> str:
    name = state["config"].get("model", {}).get("name", "aniformer")
    if name == "npt":
        return "NPT"
    return "regression head" if model.config.head == "regression" else "AniFormer"


def _default_name(reference: str) -> str:
    if reference.startswith("models:/"):  # a registered model: models:/aniformer/3 -> aniformer-3
        return re.sub(r"[/@]", "-", reference.removeprefix("models:/").rstrip("/"))
    from pipeline.tracking import RUN_ID

    match = RUN_ID.fullmatch(reference)
    if match and not Path(reference).exists():
        return match.group(1)[:8]
    path = Path(reference).resolve()
    return (path.parent.name if path.is_file() else path.name) or "checkpoint"


def refusals_line(refused: dict[str, list[bool]]) -> str:
    """--targets: how many of each variant's model results the self-check refused, as one line."""
    counts = ", ".join(f"`{variant}` {sum(values)}/{len(values)}" for variant, values in refused.items())
    return f"Refused by the self-check (aniformer/trust.py), of the model's results: {counts}."


def results_report(options: EvaluateOptions, state: dict, table: dict, spread: dict, sweep, levels, data: EvalData, *,
                   seconds: float, refused: dict[str, list[bool]] | None = None,
                   accelerations: dict | None = None) -> tuple[str, dict]:
    """The results as Markdown (mean and SD tables with each model's ratios, the acceleration errors, the
    noise sweep, --targets' refusals) and as the results.json record."""
    from aniformer.io.report import table_markdown

    splits, pairs, seed, noise_split, clip_frames = data.splits, data.pairs, data.seed, data.noise_split, data.clip_frames
    notes = [*data.notes, f"{pairs} pairs per split (seed {seed}, window as each model's, vertex shuffling "
                          f"'{data.source.shuffle}'; copy-driver on the same pairs unshuffled). Checkpoint: "
                          f"{options.checkpoint} (epoch {state.get('epoch')}); data: {data.label}."]
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
    result = {"checkpoint": options.checkpoint, "data": data.label, "pairs": pairs, "seed": seed,
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


def write_results(out: Path, options: EvaluateOptions, markdown: str, result: dict, table: dict, sweep, config: dict,
                  name: str) -> str | None:
    """results.md/.csv/.json (and the noise sweep's CSV and plot), staged, and the MLflow run; its id."""
    from aniformer.io.report import plot_sweep, sweep_csv, table_csv

    splits, pairs, seed = result["splits"], result["pairs"], result["seed"]
    with staged_output_dir(out, options.overwrite) as tmp:
        (tmp / "results.md").write_text(markdown)
        (tmp / "results.csv").write_text(table_csv(table, splits))
        (tmp / "results.json").write_text(json.dumps(result, indent=2) + "\n")
        if sweep is not None:
            (tmp / "noise.csv").write_text(sweep_csv(sweep))
            plot_sweep(sweep, tmp / "noise.png", result["noise"]["split"])
        run_id = None
        if not options.no_mlflow:
            run_id = _log_to_mlflow(f"evaluate-{name}", options, out, tmp, table, sweep, pairs, seed, splits, config,
                                    result.get("acceleration"))

    return run_id


def load_models(checkpoint: str, compare: list) -> tuple[Path, object, dict, list]:
    """(the checkpoint's path, its model, its state, the --compare rows (label, model))."""
    from aniformer.checkpoint import model_from_checkpoint
    from pipeline.registry import resolve_checkpoint

    with tempfile.TemporaryDirectory(prefix="aniformer-eval-") as scratch:
        ckpt_path = resolve_checkpoint(checkpoint, Path(scratch))
        model, state = model_from_checkpoint(ckpt_path)
        others = [(label, model_from_checkpoint(resolve_checkpoint(reference, Path(scratch)))[0])
                  for label, reference in compare]
    return ckpt_path, model, state, others


def contenders_of(options: EvaluateOptions, rows: list, window: int, device):
    """The rows' models, then (unless --no-copy-driver) the three baselines and (--skinned-transfer) the skinned
    transfer, under unique names."""
    from aniformer.evaluate import (
        SKINNED,
        copy_driver_contender,
        model_contender,
        skinned_transfer_contender,
        static_target_contender,
        transfer_contender,
    )

    baselines = [] if options.no_copy_driver else ["copy-driver", "static target", "deformation transfer"]
    labels = [r[0] for r in rows] + baselines + ([SKINNED] if options.skinned_transfer else [])
    if len(set(labels)) != len(labels):
        raise UserError(f"row names must be unique, got {', '.join(labels)}")
    contenders = [model_contender(label, m, device) for label, m in rows]
    if not options.no_copy_driver:  # one topology per bank or stream: driver and target always correspond
        contenders += [copy_driver_contender(window), static_target_contender(window), transfer_contender(window)]
    if options.skinned_transfer:
        contenders.append(skinned_transfer_contender(window))
    return contenders


def score(options: EvaluateOptions, rows, contenders, data: EvalData, levels, device):
    """({row: {split: per-pair PMDs}}, the noise sweep or None, --targets: {variant: per pair, whether the
    self-check refused the model's result} or None, ``data.clip_frames``: {row: {split: per-clip acceleration
    errors}} or None), with a progress bar on stderr."""
    from tqdm import tqdm

    from aniformer.evaluate import (
        DEFAULT_CLIP_PAIRS,
        SKINNED,
        Samplers,
        clip_accelerations,
        evaluate_pairs,
        noise_sweep,
        target_pmds,
    )

    model, splits, pairs, seed = rows[0][1], data.splits, data.pairs, data.seed
    if options.targets is not None:
        refused: dict[str, list[bool]] = {}
        with tqdm(total=pairs, unit="pair", desc="evaluate targets", disable=options.no_progress, file=sys.stderr) as bar:
            scores = target_pmds(model, data.sampler(model.config.window, "none"), options.target_split, splits,
                                 pairs=pairs, device=device, batch_size=options.batch_size,
                                 progress=lambda: bar.update(1), refused=refused, skinned=options.skinned_transfer)
        return {rows[0][0]: scores.pop("model"), **scores}, None, refused, None
    samplers = Samplers(data.sampler, data.source.shuffle)
    steps = len(contenders) * (len(splits) + (len(levels) if levels else 0)) + (len(splits) if data.clip_frames else 0)
    with tqdm(total=steps, unit="split", desc="evaluate", disable=options.no_progress, file=sys.stderr) as bar:
        scores = evaluate_pairs(contenders, samplers, splits, pairs=pairs, batch_size=options.batch_size, seed=seed,
                                progress=lambda *_: bar.update(1))
        sweep = None if levels is None else noise_sweep(contenders, samplers, data.noise_split, levels, pairs=pairs,
                                                        batch_size=options.batch_size, seed=seed,
                                                        progress=lambda *_: bar.update(1))
        accelerations = None
        if data.clip_frames:
            clips = data.sampler(data.clip_frames, "none")
            clip_pairs = options.clip_pairs or min(pairs, DEFAULT_CLIP_PAIRS)
            sliding = [c for c in contenders if c.name != SKINNED]  # a fit per frame of every window: hours
            accelerations = {c.name: {} for c in sliding}
            for split in splits:
                for name, values in clip_accelerations(sliding, clips, split, pairs=clip_pairs).items():
                    accelerations[name][split] = values
                bar.update(1)
    return scores, sweep, None, accelerations


def _log_to_mlflow(job: str, options: EvaluateOptions, out: Path, files: Path, table, sweep, pairs, seed, splits, config,
                   acceleration=None) -> str:
    from pipeline.tracking import RUN_ID, quiet_mlflow, start_job_run

    quiet_mlflow()

    params = {"evaluate": {"checkpoint": options.checkpoint, "bank": str(options.bank or ""),
                           "topology": options.topology or "", "pairs": pairs, "seed": seed, "splits": splits,
                           "clip_frames": options.clip_frames, "clip_pairs": options.clip_pairs,
                           "compare": options.compare, "noise": options.noise or ""}, **config}
    try:
        tracker = start_job_run(job, params, experiment=options.experiment, out=out)
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
            source = RUN_ID.fullmatch(options.checkpoint)
            if source and not Path(options.checkpoint).exists():
                tracker.set_tags({"aniformer.source_run": source.group(1)})
    except UserError:
        raise
    except Exception as e:  # unreachable server, bad URI ...
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise UserError(f"MLflow logging failed ({first[:200]}); rerun with --no-mlflow to skip it") from None
    return tracker.run_id


def _metric_name(label: str) -> str:
    return re.sub(r"[^0-9A-Za-z_\-.]+", "_", label)

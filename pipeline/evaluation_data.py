"""What jobs/evaluate.py scores a checkpoint on (`choose_data`): its stream's splits, variants of a stream
split's targets (``--targets``) or a mesh bank's splits, as an `EvalData`."""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from aniformer.errors import UserError

if TYPE_CHECKING:
    from collections.abc import Sequence

    from pipeline.data import DataConfig, PairSource
    from pipeline.evaluation import EvaluateOptions


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


def choose_data(options: EvaluateOptions, ckpt_path: Path, config: dict, levels) -> EvalData:
    """What a checkpoint is scored on, from its run config and the flags: the target variants (--targets),
    its stream (a stream checkpoint without --bank), or a bank."""
    from pipeline.data import data_config

    cfg = data_config(config)
    pairs, seed = options.pairs or cfg.eval_pairs, cfg.seed if options.seed is None else options.seed
    if options.targets is not None:
        data = _target_data(options, cfg, pairs, seed)
    elif cfg.source == "stream" and not options.bank:
        data = _stream_data(options, cfg, pairs, seed)
    else:
        data = _bank_data(options, ckpt_path, cfg, pairs, seed)
    if options.clip_frames and not data.clip_frames:
        raise UserError("--clip-frames applies to the splits of a stream checkpoint (no --bank, no --targets)")
    return _with_splits(options, data, levels)


def _with_splits(options: EvaluateOptions, data: EvalData, levels) -> EvalData:
    """``data`` with the columns to score (--splits, else all) and the noise sweep's split."""
    columns = data.columns
    splits = [s.strip() for s in options.splits.split(",")] if options.splits else list(columns)
    unknown = [s for s in splits if s not in columns]
    if unknown or not splits:
        raise UserError(f"--splits: unknown split(s) {', '.join(unknown) or '(none given)'}; "
                        f"the data has {', '.join(columns)}")
    noise_split = options.noise_split or ("unseen" if "unseen" in splits else splits[-1])
    if levels is not None and noise_split not in columns:
        raise UserError(f"--noise-split {noise_split!r} is not a split of the data ({', '.join(columns)})")
    return dataclasses.replace(data, splits=splits, noise_split=noise_split)


def _columns(source: PairSource) -> dict[str, str]:
    """The splits pairs can be drawn from, name -> description."""
    return {s: source.splits[s] for s in source.non_empty_splits}


def _stream(options: EvaluateOptions, cfg: DataConfig) -> PairSource:
    """The checkpoint's stream, on --topology if given."""
    from aniformer.synth.bodies import TOPOLOGIES
    from pipeline.data import pair_source

    topology = options.topology or cfg.topology
    if topology not in TOPOLOGIES:
        raise UserError(f"--topology must be one of {', '.join(TOPOLOGIES)}; got {topology!r}")
    return pair_source(cfg, None, topology)


def _stream_data(options: EvaluateOptions, cfg: DataConfig, pairs: int, seed: int) -> EvalData:
    """The stream's splits, made on the fly, and the acceleration error's clips."""
    from aniformer.evaluate import DEFAULT_CLIP_FRAMES
    from aniformer.synth.poses import LIBRARY_FRAMES

    source = _stream(options, cfg)
    clip_frames = DEFAULT_CLIP_FRAMES if options.clip_frames is None else options.clip_frames
    if clip_frames > LIBRARY_FRAMES:
        raise UserError(f"--clip-frames must be at most {LIBRARY_FRAMES} (the stream's longest clip), got {clip_frames}")
    return EvalData(source, pairs, seed, f"stream, topology {source.topology}", _columns(source), clip_frames=clip_frames)


def _target_data(options: EvaluateOptions, cfg: DataConfig, pairs: int, seed: int) -> EvalData:
    """``--targets``: variants of the targets of one stream split, as the columns."""
    from aniformer.synth.variants import DRIVER_FRAMES, VARIANTS

    if cfg.source != "stream" or options.bank or options.compare or options.noise:
        raise UserError("--targets scores a stream checkpoint alone: no --bank, --compare or --noise")
    source = _stream(options, cfg)
    if options.target_split not in source.splits:
        raise UserError(f"--target-split {options.target_split!r}: known splits are {', '.join(source.splits)}")
    variants = [v.strip() for v in options.targets.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or not variants:
        raise UserError(f"--targets: unknown variant(s) {', '.join(unknown) or '(none given)'}; known: {', '.join(VARIANTS)}")
    notes = [f"Targets of split `{options.target_split}` ({source.splits[options.target_split]}); the model and "
             "the deformation transfer reach targets of other topologies through aniformer/registration.py, "
             "the copy-driver is carried to the target's vertices through the ground-truth correspondence."]
    if "foreign_driver" in variants:
        notes.append(f"`foreign_driver`: the driver is registered on its whole {DRIVER_FRAMES}-frame clip "
                     "(aniformer/correspondence.py: register_clip), and the model slides its window over the clip "
                     "(aniformer/animate.py); every frame is scored.")
    return EvalData(source, pairs, seed, f"stream, topology {source.topology}", {v: VARIANTS[v] for v in variants}, notes)


def _bank_data(options: EvaluateOptions, ckpt_path: Path, cfg: DataConfig, pairs: int, seed: int) -> EvalData:
    """The splits with pairs of a mesh bank: --bank, else bank/ beside the checkpoint."""
    from pipeline.data import load_bank, pair_source

    if options.topology:
        raise UserError("--topology applies to checkpoints trained on a stream (data.source: stream)")
    bank_dir = _bank_dir(options, ckpt_path)
    bank = load_bank(bank_dir)
    # a stream checkpoint too, given --bank (the bank's one topology)
    source = pair_source(dataclasses.replace(cfg, source="bank", extra_topologies=()), bank)
    named = [s.strip() for s in (options.splits or "").split(",")]
    empty = [s for s in named if s in source.splits and s not in source.non_empty_splits]
    if empty:
        raise UserError(f"--splits: split(s) {', '.join(empty)} are empty in this bank")
    return EvalData(source, pairs, seed, f"bank {bank_dir.resolve()}", _columns(source), _bank_notes(cfg, bank.manifest))


def _bank_dir(options: EvaluateOptions, ckpt_path: Path) -> Path:
    """--bank, else bank/ beside the checkpoint file."""
    if options.bank:
        return Path(options.bank).expanduser()
    if not Path(os.path.expanduser(options.checkpoint)).exists():
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

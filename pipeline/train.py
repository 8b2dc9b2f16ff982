"""Ray Train's per-worker loop: distributed data-parallel AniFormer training.

`train_func` is the loop handed to `ray.train.torch.TorchTrainer` (DDP over gloo on CPU, nccl on GPU), in
named steps: `restore`, then per epoch `train_epoch`, `validate_and_checkpoint` (rank 0) and
`ray.train.report`. What it trains is one `TrainLoop` (the driver's `pipeline.trainer` makes it). A restored
worker resumes from the checkpoint Ray Train hands it via `get_checkpoint()` (`pipeline.checkpoints`).

One pass over the "train" dataset covers every remaining epoch (pairs of epoch e are seeded by (seed, e));
each worker takes a fixed number of batches per epoch so that all DDP ranks step in lockstep. With
`data.extra_topologies` each topology has its own datasets and batches take them in turn, one topology per batch.
"""

from __future__ import annotations

import itertools
import math
import resource
import tempfile
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import ray.train
import torch

from aniformer.checkpoint import FILENAME, save_checkpoint, unwrap
from aniformer.losses import loss_terms
from aniformer.metrics import PMD_SCALE, pmd
from aniformer.model import attention_kernels
from aniformer.models import build_model
from pipeline.checkpoints import restore_state
from pipeline.console import Console, EpochBar, epoch_line, quiet_ray, show
from pipeline.run_spec import EVAL_SPLITS, RunSpec, resolve_precision
from pipeline.tracking import Tracker

LOOP_KEY = "loop"  # Ray Train's train_loop_config is a dict: the TrainLoop travels under this key


@dataclass(frozen=True)
class TrainLoop:
    """What every worker's `train_func` trains: the run, the bank's faces (filmstrips), where the train dataset
    starts, and who it reports to."""

    spec: RunSpec
    faces: np.ndarray
    first_epoch: int = 0  # the train dataset's first epoch (the driver's resume point)
    resumed_epoch: int = 0  # the epoch the driver's own restart (a re-run job) resumed from
    tracker: Tracker | None = None
    console: Console | None = None  # None leaves Ray's output as it is and prints nothing
    placement_group_file: str | None = None  # a sweep trial's: where rank 0 records its placement group


def dataset_name(split: str, topology: str, spec: RunSpec) -> str:
    """Ray Train's name for the dataset of ``split`` on ``topology``: the split itself on the config's topology."""
    return split if topology == spec.data.topology else f"{split}_{topology}"


def topology_steps(spec: RunSpec, world: int) -> int:
    """Each topology's batches per epoch on every worker (the epoch is ``len(train_topologies)`` times that)."""
    return max(1, spec.data.pairs_per_epoch // (len(spec.data.train_topologies) * spec.train.batch_size * world))


def peak_memory_gb(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # Linux: KiB


@torch.no_grad()
def evaluate_split(model, batches, frames: slice, device, autocast) -> tuple[float, dict | None]:
    """Mean PMD (x1e4) over a split; also returns the first batch and its prediction for rendering."""
    model.eval()
    total, count, first = 0.0, 0, None
    for batch in batches:
        driving, target = batch["driving"].to(device), batch["target"].to(device)
        with autocast:
            pred = model(driving, target, batch["target_faces"].to(device)).float()
        gt = batch["ground_truth"].to(device)[:, frames]
        total += pmd(pred, gt).item() * len(pred)
        count += len(pred)
        if first is None:
            first = {k: v[:1].cpu() for k, v in batch.items()} | {"prediction": pred[:1].cpu()}
    model.train()
    return total / max(count, 1) * PMD_SCALE, first


def render_example(example: dict, frames: slice, bank_faces: np.ndarray, path: Path) -> Path:
    from aniformer.io.render import render_filmstrip

    faces = example["target_faces"][0].numpy()
    window = example["driving"].shape[1]
    target = example["target"][0].numpy()[None].repeat(window, 0)
    rows = [("driver", example["driving"][0].numpy(), bank_faces), ("target", target, faces),
            ("prediction", example["prediction"][0].numpy(), faces),
            ("ground truth", example["ground_truth"][0, frames].numpy(), faces)]
    return render_filmstrip(rows, path, frames=window)


@dataclass
class Training:
    """What a worker trains with: the model (DDP-wrapped), its optimiser state and precision, and
    where it stands (``epoch`` done, optimiser ``step``)."""

    model: torch.nn.Module
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    scaler: torch.amp.GradScaler
    autocast: torch.autocast
    precision: str
    device: torch.device
    frames: slice
    epoch: int = 0
    step: int = 0


def restore(spec: RunSpec) -> Training:
    """Build the model and optimiser, restored from Ray Train's checkpoint when there is one (a worker
    restart, or a re-run job), then wrap the model for DDP and move it to this worker's device."""
    cfg = spec.train
    torch.manual_seed(cfg.seed)  # same initial weights on every rank (DDP also broadcasts them)
    model = build_model(spec.model)
    model.activation_checkpointing = cfg.activation_checkpointing
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, list(cfg.milestones), cfg.lr_decay)
    checkpoint = ray.train.get_checkpoint()
    state = restore_state(checkpoint) if checkpoint else None
    if state:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["rng"])
    model = ray.train.torch.prepare_model(model)
    if cfg.compile != "none":  # compiled around DDP, so that DDP's buckets split the graph (DDPOptimizer)
        model = torch.compile(model, mode=cfg.compile)
    device = ray.train.torch.get_device()
    precision = resolve_precision(cfg.precision, device.type, device.type == "cuda" and torch.cuda.is_bf16_supported())
    dtype = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(precision)
    return Training(model, optimizer, scheduler, torch.amp.GradScaler(device.type, enabled=precision == "fp16"),
                    torch.autocast(device.type, dtype=dtype, enabled=dtype is not None), precision, device,
                    spec.model.output_frames(), *((state["epoch"], state["step"]) if state else (0, 0)))


def train_epoch(run: Training, spec: RunSpec, batches, steps: int, world: int, bar: EpochBar) -> dict:
    """One epoch of ``steps`` batches on this worker; returns the epoch's metrics (losses averaged over ranks)."""
    cfg, model = spec.train, run.model
    sums, waited, started = defaultdict(float), 0.0, time.perf_counter()
    for i in range(steps):
        tick = time.perf_counter()
        batch = next(batches)
        waited += time.perf_counter() - tick
        # One worker reads the dataset whole: its epochs and the restored state must agree (DDP ranks read splits).
        if world == 1 and i == 0 and int(batch["epoch"][0]) != run.epoch:
            raise RuntimeError(f"epoch {run.epoch + 1} got the pairs of epoch {int(batch['epoch'][0]) + 1}")
        driving, target = batch["driving"], batch["target"]
        update = (i + 1) % cfg.grad_accumulation == 0 or i + 1 == steps
        # DDP all-reduces gradients on every backward unless told not to: only on update steps.
        with nullcontext() if update or world == 1 else model.no_sync():
            with run.autocast, attention_kernels(cfg.attention_kernels):
                pred = model(driving, target, batch["target_faces"])
            terms = loss_terms(pred.float(), batch["ground_truth"][:, run.frames], driving[:, run.frames], target,
                               batch["target_faces"], spec.loss)
            run.scaler.scale(terms["total"] / cfg.grad_accumulation).backward()
        if update:
            run.scaler.step(run.optimizer)
            run.scaler.update()
            run.optimizer.zero_grad(set_to_none=True)
            run.step += 1
        for name, value in terms.items():
            sums[name] += value.detach()
        bar.step(lambda total=sums["total"], n=i + 1: total.item() / n)  # read only when the bar redraws
    bar.close()
    run.scheduler.step()
    run.epoch += 1
    elapsed = time.perf_counter() - started
    losses = torch.stack([sums[k] for k in ("total", "rec", "motion", "appearance")]) / steps
    if torch.distributed.is_initialized():  # average the epoch's losses over ranks
        torch.distributed.all_reduce(losses)
        losses /= world
    return {"epoch": run.epoch, "step": run.step, "loss": losses[0].item(), "loss_rec": losses[1].item(),
            "loss_motion": losses[2].item(), "loss_appearance": losses[3].item(),
            "lr": run.scheduler.get_last_lr()[0], "samples_per_s": steps * cfg.batch_size * world / elapsed,
            "data_wait_fraction": waited / elapsed, "peak_memory_gb": peak_memory_gb(run.device)}


def validate_and_checkpoint(run: Training, spec: RunSpec, metrics: dict, directory: Path, tracker: Tracker | None,
                            faces: np.ndarray) -> ray.train.Checkpoint:
    """Rank 0: PMD on the evaluation splits into ``metrics``, the checkpoint written to ``directory``, the
    metrics (and every ``render_every`` epochs a filmstrip) logged to the run."""
    cfg, example, topologies = spec.train, None, spec.data.train_topologies
    for split in EVAL_SPLITS:
        scores = {}
        for topology in topologies:
            shard = ray.train.get_dataset_shard(dataset_name(split, topology, spec)).iter_torch_batches(
                batch_size=16, device=run.device)
            with attention_kernels(cfg.attention_kernels):  # eager whatever `compile` says: other shapes
                scores[topology], first = evaluate_split(unwrap(run.model), shard, run.frames, run.device, run.autocast)
            if topology == spec.data.topology:
                example = example if split == "seen" and example else first
        metrics[f"pmd_{split}"] = float(np.mean(list(scores.values())))  # what the best checkpoint is chosen by
        if len(topologies) > 1:
            metrics |= {f"pmd_{split}_{topology}": score for topology, score in scores.items()}
    save_checkpoint(directory / FILENAME, config=spec.to_dict(), model=run.model, optimizer=run.optimizer,
                    scheduler=run.scheduler, epoch=run.epoch, step=run.step)
    if tracker:
        tracker.log_metrics(metrics, step=run.epoch)
        if example is not None and (run.epoch % cfg.render_every == 0 or run.epoch == cfg.epochs):
            tracker.log_artifact(render_example(example, run.frames, faces, directory / f"epoch_{run.epoch:04d}.png"),
                                 "filmstrips")
    return ray.train.Checkpoint.from_directory(directory)


def interleave(iterables: list) -> Iterator[dict]:
    """Batches of each iterable in turn (one topology per batch), until the first runs out."""
    return itertools.chain.from_iterable(zip(*iterables))


def train_func(loop_config: dict) -> None:
    """The per-worker training loop: restore, then per epoch train, validate and checkpoint (rank 0), report."""
    loop: TrainLoop = loop_config[LOOP_KEY]
    spec, tracker, console, first_epoch = loop.spec, loop.tracker, loop.console, loop.first_epoch
    cfg = spec.train
    quiet_ray(verbose=console is None or console.verbose)
    context = ray.train.get_context()
    rank, world = context.get_world_rank(), context.get_world_size()
    if not cfg.use_gpu:
        torch.set_num_threads(math.ceil(cfg.cpus_per_worker))
    run = restore(spec)
    if run.epoch < first_epoch:
        raise RuntimeError(f"restored epoch {run.epoch}, but the train dataset starts at epoch {first_epoch}")
    topologies = spec.data.train_topologies
    steps = len(topologies) * topology_steps(spec, world)
    batches = interleave([ray.train.get_dataset_shard(dataset_name("train", t, spec)).iter_torch_batches(
        batch_size=cfg.batch_size, drop_last=True, device=run.device, prefetch_batches=2) for t in topologies])
    for _ in range((run.epoch - first_epoch) * steps):  # a worker restart: skip the epochs since the dataset's start
        next(batches)
    if tracker and rank == 0:
        tracker.set_tags({"precision": run.precision, "device": str(run.device), "world_size": world})
        if run.epoch:  # a restore (worker failure or a re-run job) is visible in the run's history
            tracker.log_metrics({"resumed_from_epoch": run.epoch}, step=run.epoch)
    if run.epoch and rank == 0 and console and console.epoch_lines:
        restarted = run.epoch > loop.resumed_epoch  # beyond the driver's own resume point
        show(f"resumed from the checkpoint of epoch {run.epoch}" + (" after a worker group restart" if restarted else ""))
    while run.epoch < cfg.epochs:
        started = time.perf_counter()
        bar = EpochBar(bool(console and console.progress and rank == 0), run.epoch + 1, cfg.epochs, steps,
                       cfg.batch_size * world)
        metrics = train_epoch(run, spec, batches, steps, world, bar)
        with tempfile.TemporaryDirectory() as directory:
            checkpoint = None
            if rank == 0:
                checkpoint = validate_and_checkpoint(run, spec, metrics, Path(directory), tracker,
                                                     loop.faces)
                if console and console.epoch_lines:
                    show(epoch_line(metrics, cfg.epochs, time.perf_counter() - started))
            ray.train.report(metrics, checkpoint=checkpoint)



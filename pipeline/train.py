"""Ray Train: distributed data-parallel AniFormer training.

`train_func` is the per-worker loop handed to `ray.train.torch.TorchTrainer` (DDP over gloo on CPU,
nccl on GPU), in named steps: `restore`, then per epoch `train_epoch`, `validate_and_checkpoint` (rank 0)
and `ray.train.report`. `build_trainer` makes the trainer: pair datasets, scaling, checkpoints (best by
unseen PMD, plus the latest) and failure handling. A job re-created with the same name and storage
resumes from its latest checkpoint (`pipeline.checkpoints`): Ray Train hands it to `train_func` via
`get_checkpoint()`, and the train dataset starts at that epoch.

One pass over the "train" dataset covers every remaining epoch (pairs of epoch e are seeded by (seed, e));
each worker takes a fixed number of batches per epoch so that all DDP ranks step in lockstep.
"""

from __future__ import annotations

import hashlib
import math
import re
import resource
import tempfile
import time
import unicodedata
from collections import defaultdict
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import ray.train
import torch
from ray.data import DataContext, ExecutionOptions
from ray.train import CheckpointConfig, FailureConfig, LoggingConfig, RunConfig, ScalingConfig
from ray.train.torch import TorchTrainer

from aniformer.checkpoint import FILENAME, save_checkpoint, unwrap
from aniformer.errors import UserError, root_cause
from aniformer.io.files import atomic_path
from aniformer.losses import loss_terms
from aniformer.metrics import PMD_SCALE, pmd
from aniformer.model import attention_kernels
from aniformer.models import build_model
from pipeline.checkpoints import SCORE, best_checkpoint, restore_state, resume_epoch
from pipeline.console import Console, EpochBar, epoch_line, quiet_ray, show
from pipeline.data import pair_dataset, pair_source, quiet_ray_data
from pipeline.ddp import LoopbackTorchConfig
from pipeline.run_spec import EVAL_SPLITS, RunSpec, resolve_precision
from pipeline.tracking import Tracker


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
    cfg, example = spec.train, None
    for split in EVAL_SPLITS:
        shard = ray.train.get_dataset_shard(split).iter_torch_batches(batch_size=16, device=run.device)
        with attention_kernels(cfg.attention_kernels):  # eager whatever `compile` says: other shapes
            metrics[f"pmd_{split}"], first = evaluate_split(unwrap(run.model), shard, run.frames, run.device,
                                                            run.autocast)
        example = example if split == "seen" and example else first
    save_checkpoint(directory / FILENAME, config=spec.to_dict(), model=run.model, optimizer=run.optimizer,
                    scheduler=run.scheduler, epoch=run.epoch, step=run.step)
    if tracker:
        tracker.log_metrics(metrics, step=run.epoch)
        if example is not None and (run.epoch % cfg.render_every == 0 or run.epoch == cfg.epochs):
            tracker.log_artifact(render_example(example, run.frames, faces, directory / f"epoch_{run.epoch:04d}.png"),
                                 "filmstrips")
    return ray.train.Checkpoint.from_directory(directory)


def train_func(loop_config: dict) -> None:
    """The per-worker training loop: restore, then per epoch train, validate and checkpoint (rank 0), report."""
    spec = RunSpec.from_config(loop_config["config"])
    cfg = spec.train
    tracker: Tracker | None = loop_config.get("tracker")
    console = Console(**loop_config["console"]) if loop_config.get("console") else None
    quiet_ray(verbose=console is None or console.verbose)
    context = ray.train.get_context()
    rank, world = context.get_world_rank(), context.get_world_size()
    if not cfg.use_gpu:
        torch.set_num_threads(math.ceil(cfg.cpus_per_worker))
    run = restore(spec)
    first_epoch = loop_config.get("first_epoch", 0)  # the train dataset's first epoch (the driver's resume point)
    if run.epoch < first_epoch:
        raise RuntimeError(f"restored epoch {run.epoch}, but the train dataset starts at epoch {first_epoch}")
    steps = max(1, spec.data.pairs_per_epoch // (cfg.batch_size * world))
    batches = iter(ray.train.get_dataset_shard("train").iter_torch_batches(
        batch_size=cfg.batch_size, drop_last=True, device=run.device, prefetch_batches=2))
    for _ in range((run.epoch - first_epoch) * steps):  # a worker restart: skip the epochs since the dataset's start
        next(batches)
    if tracker and rank == 0:
        tracker.set_tags({"precision": run.precision, "device": str(run.device), "world_size": world})
        if run.epoch:  # a restore (worker failure or a re-run job) is visible in the run's history
            tracker.log_metrics({"resumed_from_epoch": run.epoch}, step=run.epoch)
    if run.epoch and rank == 0 and console and console.epoch_lines:
        restarted = run.epoch > loop_config.get("resumed_epoch", first_epoch)  # beyond the driver's own resume point
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
                                                     loop_config["faces"])
                if console and console.epoch_lines:
                    show(epoch_line(metrics, cfg.epochs, time.perf_counter() - started))
            ray.train.report(metrics, checkpoint=checkpoint)


def ray_run_name(name: str) -> str:
    """Ray Train's name for the run of job `name`, and its directory under the storage path. Ray Train
    tags its metrics with it and encodes them as ASCII (a non-ASCII name failed the run with a
    UnicodeEncodeError). A printable ASCII name is kept as it is. Any other gets its ASCII letters and
    digits plus the first 8 hex digits of the name's SHA-256: the same name gives the same directory
    in every run, so a rerun resumes, and names differing only outside ASCII stay apart."""
    if name.isascii() and name.isprintable():
        return name
    letters = unicodedata.normalize("NFKD", name).encode("ascii", "ignore").decode()
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", letters).strip("-.")
    digest = hashlib.sha256(name.encode()).hexdigest()[:8]
    return f"{slug}-{digest}" if slug else digest


def build_trainer(spec: RunSpec, bank_dir: Path, storage: Path, name: str, tracker: Tracker | None,
                  faces: np.ndarray, *, loop=train_func, loop_config: dict | None = None,
                  callbacks: list | None = None, console: Console | None = None) -> TorchTrainer:
    """The TorchTrainer of a run: pair datasets from the bank, scaling, checkpoints (best by unseen
    PMD, plus the latest) and failure handling. Checkpoints live under `storage/ray_run_name(name)`
    (`name` itself when it is ASCII) and a trainer re-created with the same name resumes from them.
    `loop`, `loop_config` (merged into the loop's config) and `callbacks` let a sweep trial add its
    own reporting to the same training. `console`
    (a training job's): rank 0's bar and epoch lines, Ray Train's log level; None leaves Ray's output as is."""
    cfg = spec.train
    quiet_ray_data()  # before the trainer: it captures the DataContext for its workers
    source = pair_source(spec.data, bank_dir)  # one bank load for every dataset
    run_name = ray_run_name(name)
    resumed_epoch = resume_epoch(storage / run_name)  # where the job's own restart (a rerun) picks up
    first_epoch = min(resumed_epoch, cfg.epochs - 1)  # a finished run's re-run trains nothing
    datasets = {"train": pair_dataset(source, "train", epochs=cfg.epochs - first_epoch, first_epoch=first_epoch)}
    for split in EVAL_SPLITS:
        datasets[split] = pair_dataset(source, split)
    # Blocks in the order of their pair ids: the same config and seed give the same batches, so the
    # same model (Ray Data otherwise yields blocks as tasks finish, and runs diverged from epoch 1).
    # ray.train.DataConfig.default_ingest_options() with preserve_order, less its deprecated exclude_resources
    # (passing it, even as the default, warns RayDeprecationWarning).
    current = DataContext.get_current().execution_options
    ingest = ExecutionOptions(resource_limits=current.resource_limits, preserve_order=True,
                              verbose_progress=current.verbose_progress)
    return TorchTrainer(
        loop,
        train_loop_config={"config": spec.to_dict(), "tracker": tracker, "faces": faces, "first_epoch": first_epoch,
                           "resumed_epoch": resumed_epoch,
                           "console": console.to_dict() if console else None, **(loop_config or {})},
        torch_config=LoopbackTorchConfig(),  # the DDP store on 127.0.0.1-only when the workers are local
        scaling_config=ScalingConfig(num_workers=cfg.workers, use_gpu=cfg.use_gpu,
                                     resources_per_worker={"CPU": cfg.cpus_per_worker},
                                     placement_strategy=cfg.placement_strategy),
        datasets=datasets,
        # One worker reads the whole stream: skip the split coordinator (half a core on a 2-core machine).
        dataset_config=ray.train.DataConfig(datasets_to_split=["train"] if cfg.workers > 1 else [], execution_options=ingest),
        run_config=RunConfig(
            name=run_name,
            storage_path=str(storage),
            callbacks=callbacks,
            checkpoint_config=CheckpointConfig(num_to_keep=cfg.keep_checkpoints, checkpoint_score_attribute=SCORE,
                                               checkpoint_score_order="min"),
            failure_config=FailureConfig(max_failures=cfg.max_failures),
            logging_config=LoggingConfig(log_level=console.train_log_level) if console else None,
        ),
    )


def fit(spec: RunSpec, bank_dir: Path, storage: Path, name: str, tracker: Tracker | None,
        faces: np.ndarray, console: Console | None = None) -> ray.train.Result:
    """Train `spec` on the pairs of `bank_dir`; checkpoints under `storage/ray_run_name(name)` (resumed if present)."""
    return build_trainer(spec, bank_dir, storage, name, tracker, faces, console=console).fit()


def ray_logs() -> str:
    """Where this Ray session's logs are (the driver's node), for error messages."""
    try:
        return ray._private.worker.global_worker.node.get_logs_dir_path()
    except Exception:
        return "/tmp/ray/session_latest/logs on the head node"


def training_failure(error: BaseException) -> str:
    """One line for a failed `fit()`: the root cause, which worker, and where the logs are."""
    cause = root_cause(error)
    failures = getattr(error, "worker_failures", None)
    where = f" on worker rank {min(failures)}" if failures else ""
    text = " ".join(str(cause).split()) if str(cause).strip() else ""
    detail = text if isinstance(cause, UserError) else f"{type(cause).__name__}" + (f": {text}" if text else "")
    return f"training failed{where}: {detail[:300]} (logs: {ray_logs()})"


def train_job(spec: RunSpec, bank_dir: Path, out: Path, name: str, tracker: Tracker,
              faces: np.ndarray, console: Console | None = None) -> ray.train.Result:
    """A training job's work (jobs/train.py, each ablation variant): `fit` with Ray's checkpoints under
    `out/ray`, then `out/best.pt` (best unseen PMD) and `out/last.pt`, the best logged to the run."""
    import shutil

    from pipeline.tracking import CHECKPOINT_ARTIFACT

    try:
        result = fit(spec, bank_dir, out / "ray", name, tracker, faces, console)
    except ray.train.TrainingFailedError as e:  # Ray Train v2's fit() raises what a worker or the controller did
        raise UserError(training_failure(e)) from None
    except ray.exceptions.RayActorError as e:  # the controller itself died (killed, its node lost)
        raise UserError(f"training interrupted: Ray Train's controller died ({type(e).__name__}); the same command "
                        f"resumes from the last checkpoint (logs: {ray_logs()})") from None
    if result.error:
        raise UserError(training_failure(result.error))
    for checkpoint, filename in ((best_checkpoint(result), "best.pt"), (result.checkpoint, "last.pt")):
        # Renamed into place: whatever stands at OUT/filename (a symlink too) is replaced, never written through.
        with checkpoint.as_directory() as directory, atomic_path(out / filename) as tmp:
            shutil.copyfile(Path(directory) / FILENAME, tmp)
    tracker.log_artifact(out / "best.pt", CHECKPOINT_ARTIFACT.rsplit("/", 1)[0])
    return result

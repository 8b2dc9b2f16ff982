"""Ray Train: distributed data-parallel AniFormer training.

`train_func` is the per-worker loop handed to `ray.train.torch.TorchTrainer` (DDP over gloo on CPU,
nccl on GPU); `fit` builds the trainer: pair datasets from the bank, scaling, checkpoints (best by
unseen PMD, plus the latest) and failure handling. A job re-created with the same name and storage
resumes from its latest checkpoint: Ray Train hands it to `train_func` via `get_checkpoint()`.

One pass over the "train" dataset covers every epoch (pairs of epoch e are seeded by (seed, e));
each worker takes a fixed number of batches per epoch so that all DDP ranks step in lockstep.
"""

from __future__ import annotations

import math
import resource
import tempfile
import time
from collections import defaultdict
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import ray.train
import torch
from ray.data import DataContext, ExecutionOptions
from ray.train import CheckpointConfig, DataConfig, FailureConfig, LoggingConfig, RunConfig, ScalingConfig
from ray.train.torch import TorchTrainer

from aniformer.baselines import MODELS, build_model
from aniformer.checkpoint import FILENAME, load_checkpoint, save_checkpoint, unwrap
from aniformer.cli import UserError, atomic_path, from_dict
from aniformer.losses import LossConfig, loss_terms
from aniformer.metrics import PMD_SCALE, pmd
from aniformer.model import ATTENTION_KERNELS, attention_kernels
from pipeline.console import Console, EpochBar, epoch_line, quiet_ray, show
from pipeline.data import DataConfig as PairDataConfig
from pipeline.data import data_config, pair_dataset, pair_source, quiet_ray_data
from pipeline.tracking import Tracker

PRECISIONS = ("auto", "fp32", "bf16", "fp16")
COMPILE_MODES = ("none", "default", "reduce-overhead", "max-autotune")  # torch.compile's modes; none = eager
EVAL_SPLITS = ("seen", "unseen")
SCORE = "pmd_unseen"


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and execution; defaults are the paper's (Adam 5e-5, MultiStep 80/120/160 x0.1)."""

    epochs: int = 200
    batch_size: int = 2
    grad_accumulation: int = 1  # optimiser step every k batches: effective batch k * batch_size * workers
    lr: float = 5e-5
    milestones: tuple[int, ...] = (80, 120, 160)
    lr_decay: float = 0.1
    seed: int = 0
    workers: int = 1
    cpus_per_worker: float = 1.0
    use_gpu: bool = False
    placement_strategy: str = "PACK"  # SPREAD puts the workers on different nodes
    precision: str = "auto"  # auto: bf16 on GPUs that have it, fp16 + GradScaler on older (V100), fp32 on CPU
    compile: str = "none"  # torch.compile mode for the training forward/backward (reduce-overhead: CUDA graphs)
    activation_checkpointing: bool = False  # model parts keep only their inputs, rerun in backward (huge V)
    attention_kernels: tuple[str, ...] = ()  # SDPA kernels allowed, by preference (e.g. cudnn, flash, efficient)
    max_failures: int = 2
    keep_checkpoints: int = 2
    render_every: int = 5

    def __post_init__(self):
        object.__setattr__(self, "milestones", tuple(self.milestones))
        object.__setattr__(self, "attention_kernels", tuple(self.attention_kernels))
        for name in ("epochs", "batch_size", "grad_accumulation", "workers", "keep_checkpoints", "render_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.lr <= 0 or self.cpus_per_worker <= 0:
            raise ValueError("lr and cpus_per_worker must be > 0")
        if self.placement_strategy not in ("PACK", "SPREAD", "STRICT_PACK", "STRICT_SPREAD"):
            raise ValueError(f"placement_strategy must be PACK, SPREAD, STRICT_PACK or STRICT_SPREAD, "
                             f"got {self.placement_strategy!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        if self.compile not in COMPILE_MODES:
            raise ValueError(f"compile must be one of {COMPILE_MODES}, got {self.compile!r}")
        unknown = sorted(set(self.attention_kernels) - set(ATTENTION_KERNELS))
        if unknown:
            raise ValueError(f"attention_kernels: unknown {unknown}; choose from {sorted(ATTENTION_KERNELS)}")


@dataclass(frozen=True)
class RunSpec:
    """A validated run config: every section parsed, so bad input fails before Ray starts."""

    data: PairDataConfig
    model_name: str
    model: object  # AniFormerConfig | NPTConfig
    loss: LossConfig
    train: TrainConfig

    @classmethod
    def from_config(cls, config: dict) -> RunSpec:
        unknown = sorted(set(config) - {"data", "model", "loss", "train"})
        if unknown:
            raise UserError(f"unknown config section(s): {', '.join(unknown)} (known: data, model, loss, train)")
        section = dict(config.get("model") or {})
        name = section.pop("name", "aniformer")
        if name not in MODELS:
            raise UserError(f"[model] unknown name {name!r}; choose one of {sorted(MODELS)}")
        model = from_dict(MODELS[name][1], section, "model")
        data = data_config(config)
        if getattr(model, "window", data.window) != data.window:
            raise UserError(f"model.window={model.window} differs from data.window={data.window}")
        return cls(data, name, model, from_dict(LossConfig, config.get("loss"), "loss"),
                   from_dict(TrainConfig, config.get("train"), "train"))

    def to_dict(self) -> dict:
        return {"data": self.data.to_dict(), "model": {"name": self.model_name, **self.model.to_dict()},
                "loss": asdict(self.loss), "train": {**asdict(self.train), "milestones": list(self.train.milestones),
                                                     "attention_kernels": list(self.train.attention_kernels)}}


def resolve_precision(requested: str, device: torch.device) -> str:
    if requested != "auto":
        return requested
    if device.type != "cuda":
        return "fp32"
    return "bf16" if torch.cuda.is_bf16_supported() else "fp16"


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
    from aniformer.render import render_filmstrip

    faces = example["target_faces"][0].numpy()
    window = example["driving"].shape[1]
    target = example["target"][0].numpy()[None].repeat(window, 0)
    rows = [("driver", example["driving"][0].numpy(), bank_faces), ("target", target, faces),
            ("prediction", example["prediction"][0].numpy(), faces),
            ("ground truth", example["ground_truth"][0, frames].numpy(), faces)]
    return render_filmstrip(rows, path, frames=window)


def train_func(loop_config: dict) -> None:
    """The per-worker training loop (see the module docstring)."""
    spec = RunSpec.from_config(loop_config["config"])
    cfg, loss_cfg = spec.train, spec.loss
    tracker: Tracker | None = loop_config.get("tracker")
    console = Console(**loop_config["console"]) if loop_config.get("console") else None
    quiet_ray(verbose=console is None or console.verbose)
    context = ray.train.get_context()
    rank, world = context.get_world_rank(), context.get_world_size()
    if not cfg.use_gpu:
        torch.set_num_threads(math.ceil(cfg.cpus_per_worker))

    torch.manual_seed(cfg.seed)  # same initial weights on every rank (DDP also broadcasts them)
    model = build_model(spec.model_name, spec.model.to_dict())
    model.activation_checkpointing = cfg.activation_checkpointing
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, list(cfg.milestones), cfg.lr_decay)
    start_epoch, step = 0, 0
    checkpoint = ray.train.get_checkpoint()
    state = restore_state(checkpoint) if checkpoint else None
    if state:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        start_epoch, step = state["epoch"], state["step"]
        torch.set_rng_state(state["rng"])
    model = ray.train.torch.prepare_model(model)
    if cfg.compile != "none":  # compiled around DDP, so that DDP's buckets split the graph (DDPOptimizer)
        model = torch.compile(model, mode=cfg.compile)
    device = ray.train.torch.get_device()
    precision = resolve_precision(cfg.precision, device)
    dtype = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(precision)
    autocast = torch.autocast(device.type, dtype=dtype, enabled=dtype is not None)
    scaler = torch.amp.GradScaler(device.type, enabled=precision == "fp16")
    frames = spec.model.output_frames()

    steps_per_epoch = max(1, spec.data.pairs_per_epoch // (cfg.batch_size * world))
    batches = iter(ray.train.get_dataset_shard("train").iter_torch_batches(
        batch_size=cfg.batch_size, drop_last=True, device=device, prefetch_batches=2))
    for _ in range(start_epoch * steps_per_epoch):  # resumed: skip the epochs the checkpoint already has
        next(batches)
    if tracker and rank == 0:
        tracker.set_tags({"precision": precision, "device": str(device), "world_size": world})
        if start_epoch:  # a restore (worker failure or a re-run job) is visible in the run's history
            tracker.log_metrics({"resumed_from_epoch": start_epoch}, step=start_epoch)

    for epoch in range(start_epoch, cfg.epochs):
        sums, waited, started = defaultdict(float), 0.0, time.perf_counter()
        bar = EpochBar(bool(console and console.progress and rank == 0), epoch + 1, cfg.epochs, steps_per_epoch,
                       cfg.batch_size * world)
        for i in range(steps_per_epoch):
            tick = time.perf_counter()
            batch = next(batches)
            waited += time.perf_counter() - tick
            driving, target = batch["driving"], batch["target"]
            update = (i + 1) % cfg.grad_accumulation == 0 or i + 1 == steps_per_epoch
            # DDP all-reduces gradients on every backward unless told not to: only on update steps.
            with nullcontext() if update or world == 1 else model.no_sync():
                with autocast, attention_kernels(cfg.attention_kernels):
                    pred = model(driving, target, batch["target_faces"])
                terms = loss_terms(pred.float(), batch["ground_truth"][:, frames], driving[:, frames], target,
                                   batch["target_faces"], loss_cfg)
                scaler.scale(terms["total"] / cfg.grad_accumulation).backward()
            if update:
                scaler.step(optimizer)
                scaler.update()
                optimizer.zero_grad(set_to_none=True)
                step += 1
            for name, value in terms.items():
                sums[name] += value.detach()
            bar.step(lambda total=sums["total"], n=i + 1: total.item() / n)  # read only when the bar redraws
        bar.close()
        scheduler.step()
        elapsed = time.perf_counter() - started
        losses = torch.stack([sums[k] for k in ("total", "rec", "motion", "appearance")]) / steps_per_epoch
        if torch.distributed.is_initialized():  # average the epoch's losses over ranks
            torch.distributed.all_reduce(losses)
            losses /= world
        metrics = {"epoch": epoch + 1, "step": step, "loss": losses[0].item(), "loss_rec": losses[1].item(),
                   "loss_motion": losses[2].item(), "loss_appearance": losses[3].item(),
                   "lr": scheduler.get_last_lr()[0],
                   "samples_per_s": steps_per_epoch * cfg.batch_size * world / elapsed,
                   "data_wait_fraction": waited / elapsed, "peak_memory_gb": peak_memory_gb(device)}
        with tempfile.TemporaryDirectory() as directory:
            report_checkpoint = None
            if rank == 0:
                example = None
                for split in EVAL_SPLITS:
                    shard = ray.train.get_dataset_shard(split).iter_torch_batches(batch_size=16, device=device)
                    with attention_kernels(cfg.attention_kernels):  # eager whatever `compile` says: other shapes
                        metrics[f"pmd_{split}"], first = evaluate_split(unwrap(model), shard, frames, device,
                                                                        autocast)
                    example = example if split == "seen" and example else first
                save_checkpoint(Path(directory) / FILENAME, config=spec.to_dict(), model=model,
                                optimizer=optimizer, scheduler=scheduler, epoch=epoch + 1, step=step)
                report_checkpoint = ray.train.Checkpoint.from_directory(directory)
                if tracker:
                    tracker.log_metrics(metrics, step=epoch + 1)
                    last = epoch + 1 == cfg.epochs
                    if example is not None and ((epoch + 1) % cfg.render_every == 0 or last):
                        png = render_example(example, frames, np.asarray(loop_config["faces"]),
                                             Path(directory) / f"epoch_{epoch + 1:04d}.png")
                        tracker.log_artifact(png, "filmstrips")
                if console and console.epoch_lines:
                    show(epoch_line(metrics, cfg.epochs, time.perf_counter() - started))
            ray.train.report(metrics, checkpoint=report_checkpoint)


def restore_state(checkpoint: ray.train.Checkpoint) -> dict | None:
    """The state to resume from: Ray's latest checkpoint, or, if that one is unreadable (truncated by
    a crash or a full disk), the newest intact checkpoint beside it; None (start afresh, said in the
    log) if none is intact."""
    with checkpoint.as_directory() as directory:
        try:
            return load_checkpoint(directory)
        except UserError as e:
            problem = str(e)
    import pyarrow.fs

    if not isinstance(checkpoint.filesystem, pyarrow.fs.LocalFileSystem):
        raise UserError(f"cannot resume: {problem}")
    latest = Path(checkpoint.path)
    for candidate in sorted(latest.parent.glob("checkpoint_*"), reverse=True):  # names sort by time
        if candidate != latest and candidate.is_dir():
            try:
                state = load_checkpoint(candidate)
            except UserError:
                continue
            print(f"resume: {problem}; resuming from the newest intact checkpoint, {candidate.name} "
                  f"(epoch {state['epoch']})", flush=True)
            return state
    print(f"resume: {problem}, and no other checkpoint of {latest.parent} is intact: starting afresh", flush=True)
    return None


def build_trainer(spec: RunSpec, bank_dir: Path, storage: Path, name: str, tracker: Tracker | None,
                  faces: np.ndarray, *, loop=train_func, loop_config: dict | None = None,
                  callbacks: list | None = None, console: Console | None = None) -> TorchTrainer:
    """The TorchTrainer of a run: pair datasets from the bank, scaling, checkpoints (best by unseen
    PMD, plus the latest) and failure handling. Checkpoints live under `storage/name` and a trainer
    re-created with the same name resumes from them. `loop`, `loop_config` (merged into the loop's
    config) and `callbacks` let a sweep trial add its own reporting to the same training. `console`
    (a training job's): rank 0's bar and epoch lines, Ray Train's log level; None leaves Ray's output as is."""
    cfg = spec.train
    quiet_ray_data()  # before the trainer: it captures the DataContext for its workers
    source = pair_source(spec.data, bank_dir)  # one bank load for every dataset
    datasets = {"train": pair_dataset(source, "train", epochs=cfg.epochs)}
    for split in EVAL_SPLITS:
        datasets[split] = pair_dataset(source, split)
    # Blocks in the order of their pair ids: the same config and seed give the same batches, so the
    # same model (Ray Data otherwise yields blocks as tasks finish, and runs diverged from epoch 1).
    # DataConfig.default_ingest_options() with preserve_order, less its deprecated exclude_resources
    # (passing it, even as the default, warns RayDeprecationWarning).
    current = DataContext.get_current().execution_options
    ingest = ExecutionOptions(resource_limits=current.resource_limits, preserve_order=True,
                              verbose_progress=current.verbose_progress)
    return TorchTrainer(
        loop,
        train_loop_config={"config": spec.to_dict(), "tracker": tracker, "faces": faces.tolist(),
                           "console": console.to_dict() if console else None, **(loop_config or {})},
        scaling_config=ScalingConfig(num_workers=cfg.workers, use_gpu=cfg.use_gpu,
                                     resources_per_worker={"CPU": cfg.cpus_per_worker},
                                     placement_strategy=cfg.placement_strategy),
        datasets=datasets,
        # One worker reads the whole stream: skip the split coordinator (half a core on a 2-core machine).
        dataset_config=DataConfig(datasets_to_split=["train"] if cfg.workers > 1 else [], execution_options=ingest),
        run_config=RunConfig(
            name=name,
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
    """Train `spec` on the pairs of `bank_dir`; checkpoints under `storage/name` (resumed if present)."""
    return build_trainer(spec, bank_dir, storage, name, tracker, faces, console=console).fit()


def root_cause(error: BaseException) -> BaseException:
    """The exception at the bottom of Ray's wrappers: a worker group's lowest failed rank, a controller's
    failure, a task error's cause, each exception's `__cause__`."""
    seen = set()
    while id(error) not in seen:
        seen.add(id(error))
        failures = getattr(error, "worker_failures", None)
        inner = (failures[min(failures)] if failures else None) or getattr(error, "controller_failure", None) \
            or getattr(error, "cause", None) or error.__cause__
        if not isinstance(inner, BaseException):
            break
        error = inner
    return error


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


def best_checkpoint(result: ray.train.Result) -> ray.train.Checkpoint:
    scored = [(m[SCORE], c) for c, m in (result.best_checkpoints or []) if math.isfinite(m.get(SCORE, math.nan))]
    return min(scored, key=lambda x: x[0])[1] if scored else result.checkpoint


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
    if result.error:
        raise UserError(training_failure(result.error))
    for checkpoint, filename in ((best_checkpoint(result), "best.pt"), (result.checkpoint, "last.pt")):
        # Renamed into place: whatever stands at OUT/filename (a symlink too) is replaced, never written through.
        with checkpoint.as_directory() as directory, atomic_path(out / filename) as tmp:
            shutil.copyfile(Path(directory) / FILENAME, tmp)
    tracker.log_artifact(out / "best.pt", CHECKPOINT_ARTIFACT.rsplit("/", 1)[0])
    return result

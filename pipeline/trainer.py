"""The driver side of a training run: the `TorchTrainer` of a run and a training job's work.

`build_trainer` makes the trainer: pair datasets, scaling, checkpoints (best by unseen PMD, plus the latest)
and failure handling, around the workers' `pipeline.train.train_func`. A job re-created with the same name and
storage resumes from its latest checkpoint (`pipeline.checkpoints`), and the train dataset starts at that epoch.
`train_job` is what jobs/train.py and each ablation variant run: `fit`, then `best.pt` and `last.pt`.
"""

from __future__ import annotations

import hashlib
import re
import unicodedata
from collections.abc import Callable
from pathlib import Path

import numpy as np
import ray.train
from ray.data import DataContext, ExecutionOptions
from ray.train import CheckpointConfig, FailureConfig, LoggingConfig, RunConfig, ScalingConfig
from ray.train.torch import TorchTrainer

from aniformer.checkpoint import FILENAME
from aniformer.errors import UserError, root_cause
from aniformer.io.files import atomic_path
from pipeline.checkpoints import SCORE, best_checkpoint, resume_epoch
from pipeline.console import Console
from pipeline.data import pair_dataset, pair_source, quiet_ray_data
from pipeline.ddp import LoopbackTorchConfig
from pipeline.run_spec import EVAL_SPLITS, RunSpec
from pipeline.tracking import Tracker
from pipeline.train import LOOP_KEY, TrainLoop, dataset_name, topology_steps, train_func


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
                  faces: np.ndarray, *, loop: Callable[[dict], None] = train_func,
                  placement_group_file: str | None = None, callbacks: list | None = None,
                  console: Console | None = None) -> TorchTrainer:
    """The TorchTrainer of a run: pair datasets from the bank, scaling, checkpoints (best by unseen
    PMD, plus the latest) and failure handling. Checkpoints live under `storage/ray_run_name(name)`
    (`name` itself when it is ASCII) and a trainer re-created with the same name resumes from them.
    `loop` (a wrapper of `train_func`), `placement_group_file` and `callbacks` let a sweep trial add its
    own reporting to the same training. `console`
    (a training job's): rank 0's bar and epoch lines, Ray Train's log level; None leaves Ray's output as is."""
    cfg = spec.train
    quiet_ray_data()  # before the trainer: it captures the DataContext for its workers
    run_name = ray_run_name(name)
    resumed_epoch = resume_epoch(storage / run_name)  # where the job's own restart (a rerun) picks up
    first_epoch = min(resumed_epoch, cfg.epochs - 1)  # a finished run's re-run trains nothing
    topologies = spec.data.train_topologies
    share = topology_steps(spec, cfg.workers) * cfg.batch_size * cfg.workers  # pairs per topology and epoch
    datasets = {}
    for i, topology in enumerate(topologies):
        source = pair_source(spec.data, bank_dir, topology)  # one bank load for every dataset
        datasets[dataset_name("train", topology, spec)] = pair_dataset(
            source, "train", epochs=cfg.epochs - first_epoch, first_epoch=first_epoch, pairs=share,
            first_index=i * share)  # each topology's own draws
        for split in EVAL_SPLITS:  # the same validation pairs at every resolution
            datasets[dataset_name(split, topology, spec)] = pair_dataset(source, split)
    # Blocks in the order of their pair ids: the same config and seed give the same batches, so the
    # same model (Ray Data otherwise yields blocks as tasks finish, and runs diverged from epoch 1).
    # ray.train.DataConfig.default_ingest_options() with preserve_order, less its deprecated exclude_resources
    # (passing it, even as the default, warns RayDeprecationWarning).
    current = DataContext.get_current().execution_options
    ingest = ExecutionOptions(resource_limits=current.resource_limits, preserve_order=True,
                              verbose_progress=current.verbose_progress)
    return TorchTrainer(
        loop,
        train_loop_config={LOOP_KEY: TrainLoop(spec, faces, first_epoch, resumed_epoch, tracker, console,
                                               placement_group_file)},
        torch_config=LoopbackTorchConfig(),  # the DDP store on 127.0.0.1-only when the workers are local
        scaling_config=ScalingConfig(num_workers=cfg.workers, use_gpu=cfg.use_gpu,
                                     resources_per_worker={"CPU": cfg.cpus_per_worker},
                                     placement_strategy=cfg.placement_strategy),
        datasets=datasets,
        # One worker reads the whole stream: skip the split coordinator (half a core on a 2-core machine).
        dataset_config=ray.train.DataConfig(
            datasets_to_split=[dataset_name("train", t, spec) for t in topologies] if cfg.workers > 1 else [],
            execution_options=ingest),
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

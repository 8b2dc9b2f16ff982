"""Ray Tune sweeps over the loss weights (eq. 6) and the window length, gated by predicted memory.

A sweep samples `loss.rec`, `loss.motion`, `loss.appearance` (log-uniform), the window T
(`data.window`) and optionally `train.lr` / `train.batch_size`, with Optuna's TPE (`search: optuna`) or
Ray's random search (`search: random`), and stops poor trials early with ASHA on the validation
PMD (`pmd_unseen`, per epoch). Every trial trains with `pipeline.train.train_func`, the loop of
jobs/train.py, in a TorchTrainer run inside a function trainable (Ray 2.60 Train V2 cannot be
passed to a Tuner directly), whose epoch reports reach Tune through `TuneReportCallback`.

Memory gate (`pipeline.memory_gate`): before a trial builds anything, `aniformer.memory` predicts its
per-worker peak. Over `memory_limit_gb` the batch is halved, with gradient accumulation keeping
the effective batch, until it fits (`adjusted_memory`); if it cannot fit (not even batch 1, or it
would need more than `max_grad_accumulation`) the trial is reported as `skipped_memory` without
being launched. The decision goes into every Tune result of the trial and into its MLflow run.

MLflow: one parent run per sweep (job = sweep name), one child run per trial (job =
`<sweep>-<trial_id>`) that receives the training curves; tags `status`, `predicted_memory_gb`,
`measured_memory_gb`, `best_pmd_unseen`; the best trial is tagged `best=true` (and named on the
parent). A driver-side Tune callback ends every child run (ASHA-stopped ones too), so no run is
left RUNNING.

Restore: the Tune experiment lives in `OUT/tune/<sweep>`; running the same sweep again restores it
with `Tuner.restore` (finished trials are kept, not rerun; unfinished ones restart and their
TorchTrainer resumes from its last checkpoint under `OUT/trials/<sweep>-<trial_id>`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from pathlib import Path

import numpy as np
import ray
import ray.train
from ray import tune
from ray.tune import Callback, CLIReporter, ExperimentAnalysis
from ray.tune.integration.ray_train import TuneReportCallback
from ray.tune.schedulers import ASHAScheduler
from ray.tune.search.basic_variant import BasicVariantGenerator
from ray.util.placement_group import PlacementGroup, placement_group_table, remove_placement_group

from aniformer.config import from_dict
from pipeline.console import Console
from pipeline.memory_gate import gate
from pipeline.run_spec import RunSpec
from pipeline.sweep_config import SweepConfig, apply_params, complete_points, search_space
from pipeline.tracking import find_job_run, start_job_run, tracking_uri
from pipeline.train import LOOP_KEY, train_func
from pipeline.trainer import build_trainer

STATUSES = ("ok", "adjusted_memory", "skipped_memory", "early_stopped", "failed")
SUMMARY_FIELDS = ("trial_id", "status", "memory_decision", "rec", "motion", "appearance", "window", "lr",
                  "batch_size", "run_batch_size", "grad_accumulation", "predicted_memory_gb",
                  "requested_memory_gb", "measured_memory_gb", "memory_limit_gb", "epochs", "best_pmd_unseen",
                  "mlflow_run_id")


def plan_trial(base: dict, params: dict, vertices: int, faces: int | None, sweep: SweepConfig):
    """(the RunSpec a trial asks for, its memory decision): what `run_trial` decides before building
    anything, and what the live table shows for a trial that has not reported yet."""
    requested = RunSpec.from_config(apply_params(base, params))
    return requested, gate(requested, vertices, faces, sweep)


def decision_fields(requested, plan, sweep: SweepConfig) -> dict:
    """The memory decision as every Tune result of the trial carries it."""
    return {"status": plan.status, "memory_decision": plan.status, "predicted_memory_gb": plan.predicted_gb,
            "requested_memory_gb": plan.requested_gb, "memory_limit_gb": sweep.memory_limit_gb or math.nan,
            "requested_batch_size": requested.train.batch_size, "run_batch_size": plan.batch_size,
            "grad_accumulation": plan.grad_accumulation}


class TrialReport(TuneReportCallback):
    """A TuneReportCallback that adds the trial's memory decision to every epoch's result."""

    def __init__(self, extra: dict):
        super().__init__()
        self.extra = extra

    def after_report(self, run_context, metrics, checkpoint):
        metrics = [{**metrics[0], **self.extra}, *metrics[1:]]
        super().after_report(run_context, metrics, checkpoint)


PLACEMENT_GROUP_FILE = "placement_group.txt"
TRIAL_CONSOLE = Console(epoch_lines=False)  # the sweep's trial table is the console; Ray Train's INFO dumps off


def sweep_train_func(loop_config: dict) -> None:
    """`pipeline.train.train_func`, after rank 0 wrote its worker group's placement group id to the
    `TrainLoop`'s `placement_group_file`.

    A trial Tune stops takes its TorchTrainer controller with it before the controller removed its
    workers' placement group, and Train V2's own cleaner can miss it (docs/sweeps.md): the sweep
    driver removes the recorded group when the trial ends (`release_placement_group`)."""
    path = loop_config[LOOP_KEY].placement_group_file
    group = ray.util.get_current_placement_group()
    if path and group is not None and ray.train.get_context().get_world_rank() == 0:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(group.id.hex())
    train_func(loop_config)


def release_placement_group(path: Path) -> bool:
    """Remove the placement group recorded in `path` if it still exists; True if one was removed."""

    if not path.is_file():
        return False
    group = PlacementGroup(ray.PlacementGroupID(bytes.fromhex(path.read_text().strip())))
    if not ray.is_initialized() or placement_group_table(group).get("state") in (None, "REMOVED"):
        return False
    remove_placement_group(group)
    return True


def run_trial(params: dict, *, base: dict, sweep: dict, sweep_name: str, bank: str, storage: str,
              experiment: str, parent_run_id: str, faces: np.ndarray, vertices: int, face_count: int,
              mlflow_uri: str) -> None:
    """The function trainable: gate (for a batch of ``vertices`` and ``face_count``: the largest topology trained
    on), open the trial's MLflow child run, train (or report the skip)."""
    # The driver's store, not one resolved in this actor (another env and cwd: Tune's trial dir).
    os.environ["MLFLOW_TRACKING_URI"] = mlflow_uri


    sweep_cfg = from_dict(SweepConfig, sweep, "sweep")
    trial_id = tune.get_context().get_trial_id()
    requested, plan = plan_trial(base, params, vertices, face_count, sweep_cfg)
    spec = dataclasses.replace(requested, train=dataclasses.replace(requested.train, batch_size=plan.batch_size,
                                                                    grad_accumulation=plan.grad_accumulation))
    name = f"{sweep_name}-{trial_id}"
    tracker = start_job_run(name, spec.to_dict(), experiment=experiment, parent_run_id=parent_run_id)
    extra = {**decision_fields(requested, plan, sweep_cfg), "mlflow_run_id": tracker.run_id}
    tracker.set_tags({"status": plan.status, "memory_decision": plan.status, "trial_id": trial_id,
                      "predicted_memory_gb": f"{plan.predicted_gb:.3f}",
                      "requested_memory_gb": f"{plan.requested_gb:.3f}",
                      "requested_batch_size": requested.train.batch_size,
                      "memory_limit_gb": sweep_cfg.memory_limit_gb or "none"})
    if plan.status == "skipped_memory":  # never built at this size: one result, no metric value
        tune.report({**extra, "epoch": 0, sweep_cfg.metric: math.nan})
        tracker.end("KILLED")
        return
    trainer = build_trainer(spec, Path(bank), Path(storage), name, tracker, faces, loop=sweep_train_func,
                            placement_group_file=str(Path(storage) / name / PLACEMENT_GROUP_FILE),
                            callbacks=[TrialReport(extra)], console=TRIAL_CONSOLE)
    result = trainer.fit()  # the driver-side SweepRuns callback ends the MLflow run with the final status
    if result.error:
        raise RuntimeError(f"trial {trial_id} failed: {type(result.error).__name__}: {result.error}")


def trial_status(metrics: dict | None, error, epochs: int) -> str:
    """One of STATUSES for a finished (or stopped) trial, from its last Tune result."""
    if error is not None:
        return "failed"
    metrics = metrics or {}
    decision = metrics.get("memory_decision")
    if decision == "skipped_memory":
        return decision
    if decision is None or int(metrics.get("epoch", 0)) < epochs:
        return "early_stopped" if decision is not None else "failed"
    return decision


MLFLOW_STATUS = {"ok": "FINISHED", "adjusted_memory": "FINISHED", "early_stopped": "KILLED",
                 "skipped_memory": "KILLED", "failed": "FAILED"}


def last_result(trial) -> dict:
    """A trial's last result without `Trial.last_result`'s ray.get of a starting actor's defaults."""
    meta = getattr(trial, "run_metadata", None)
    return dict(meta.last_result if meta is not None else trial.last_result or {})


def comparison_metrics(trial, metric: str) -> dict:
    """What a trial's child run gets when the trial ends, for the compare view (one value per run):
    `best_<metric>` (its minimum over the epochs: the last epoch's `pmd_unseen` is not the trial's
    best) and `predicted_memory_gb` (numeric, so it can be an axis; the tag of that name is text)."""
    values = {}
    best = (getattr(trial, "metric_analysis", None) or {}).get(metric, {}).get("min")
    if best is not None and math.isfinite(best):
        values[f"best_{metric}"] = float(best)
    predicted = last_result(trial).get("predicted_memory_gb")
    if predicted is not None and math.isfinite(predicted):
        values["predicted_memory_gb"] = float(predicted)
    return values


class SweepRuns(Callback):
    """Driver-side: end each trial's MLflow child run with its final status as the trial ends
    (also ASHA-stopped trials, whose trainable is stopped before it could do so itself). The run is
    found by job name, so a trial that failed before its first report is ended too."""

    def __init__(self, epochs: int, sweep_name: str, trials_dir: str, experiment: str, metric: str = "pmd_unseen"):
        self.epochs, self.sweep_name, self.trials_dir, self.experiment = epochs, sweep_name, trials_dir, experiment
        self.metric = metric

    def _end(self, trial, error) -> None:
        try:  # a callback that raises would fail the trial: report and go on
            self._release_and_end(trial, error)
        except Exception as e:
            print(f"sweep: could not finalise trial {trial.trial_id}: {type(e).__name__}: {e}", flush=True)

    def _release_and_end(self, trial, error) -> None:
        release_placement_group(Path(self.trials_dir) / f"{self.sweep_name}-{trial.trial_id}" / PLACEMENT_GROUP_FILE)
        run = find_job_run(f"{self.sweep_name}-{trial.trial_id}", self.experiment)
        if run is None:  # stopped before its trainable opened the run
            return
        metrics = trial.last_result or {}
        status = trial_status(metrics, error, self.epochs)
        tags = {"status": status}
        if "peak_memory_gb" in metrics:
            tags["measured_memory_gb"] = f"{metrics['peak_memory_gb']:.3f}"
        run.set_tags(tags)
        run.log_metrics(comparison_metrics(trial, getattr(self, "metric", "pmd_unseen")), step=int(metrics.get("epoch", 0) or 0))
        run.end(MLFLOW_STATUS[status])

    def on_trial_complete(self, iteration, trials, trial, **info):
        self._end(trial, None)

    def on_trial_error(self, iteration, trials, trial, **info):
        print(f"sweep: trial {trial.trial_id} failed: {error_line(trial.error_file)}", flush=True)
        self._end(trial, trial.error_file or "error")


def error_line(error_file: str | None) -> str:
    """A failed trial's exception in one line (the last line of the traceback Tune saved), and where the
    whole traceback is."""
    if not error_file:
        return "no error file"
    try:
        lines = [line.strip() for line in Path(error_file).read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return f"see {error_file}"
    return f"{lines[-1][:300] if lines else 'an empty error file'} (traceback: {error_file})"


class _NoTrialTracebacks(logging.Filter):
    """Drops Tune's "Trial task failed for trial ..." traceback: ``SweepRuns`` says it in one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("Trial task failed for trial")


logging.getLogger("ray.tune.execution.tune_controller").addFilter(_NoTrialTracebacks())


def build_tuner(base: dict, sweep: SweepConfig, *, sweep_name: str, out: Path, bank: Path, experiment: str,
                parent_run_id: str, faces: np.ndarray, vertices: int, face_count: int, restore: bool,
                reporter: CLIReporter):
    """A new Tuner for the sweep, or the interrupted one restored from `out/tune/<sweep_name>`; `reporter`
    draws the console's trial table (`pipeline.sweep_table.SweepReporter`)."""

    spec = RunSpec.from_config(base)
    trainable = tune.with_resources(
        tune.with_parameters(run_trial, base=base, sweep=sweep.to_dict(), sweep_name=sweep_name, bank=str(bank),
                             storage=str(out / "trials"), experiment=experiment, parent_run_id=parent_run_id,
                             faces=np.asarray(faces), vertices=int(vertices), face_count=int(face_count),
                             mlflow_uri=tracking_uri()),
        {"CPU": sweep.trial_cpus})
    path = out / "tune" / sweep_name
    # The sweep's own trial table (`reporter`). Ray 2.60's default console ("new output",
    # RAY_AIR_NEW_OUTPUT=1) ignores a RunConfig's progress_reporter; the reporter protocol is
    # honoured with the new output off. Read by Tuner.fit in this process only.
    os.environ["RAY_AIR_NEW_OUTPUT"] = "0"
    if restore:  # the run config (reporter and callbacks included) is the one saved with the experiment
        return tune.Tuner.restore(str(path), trainable, resume_unfinished=True, resume_errored=True)
    points = complete_points(sweep, spec.train.batch_size)
    if sweep.search == "optuna":
        from ray.tune.search.optuna import OptunaSearch

        search = OptunaSearch(points_to_evaluate=points or None, seed=sweep.seed)
    else:
        search = BasicVariantGenerator(points_to_evaluate=points or None, random_state=sweep.seed)
    scheduler = ASHAScheduler(time_attr="epoch", max_t=spec.train.epochs, grace_period=sweep.grace_period,
                              reduction_factor=sweep.reduction_factor)
    return tune.Tuner(
        trainable,
        param_space=search_space(sweep),
        tune_config=tune.TuneConfig(metric=sweep.metric, mode="min", search_alg=search, scheduler=scheduler,
                                    num_samples=sweep.num_samples, max_concurrent_trials=sweep.max_concurrent),
        run_config=tune.RunConfig(name=sweep_name, storage_path=str(out / "tune"),
                                  callbacks=[SweepRuns(spec.train.epochs, sweep_name, str(out / "trials"), experiment,
                                                       sweep.metric)],
                                  failure_config=tune.FailureConfig(max_failures=0),
                                  progress_reporter=reporter,
                                  verbose=1),  # legacy verbosity 1: the reporter's table, no per-result dumps
    )


def experiment_exists(out: Path, sweep_name: str) -> bool:
    path = out / "tune" / sweep_name
    return path.is_dir() and tune.Tuner.can_restore(str(path))


def unfinished_trials(experiment: Path, num_samples: int) -> list[str]:
    """Trial ids an interrupted sweep left to do, from the experiment state Tune saved (what
    `Tuner.restore` will read): trials neither terminated nor errored, plus "(not created)" for each
    sample the search had not produced yet."""

    trials = ExperimentAnalysis(str(experiment)).trials
    left = [t.trial_id for t in trials if t.status not in ("TERMINATED", "ERROR")]
    return left + ["(not created)"] * max(0, num_samples - len(trials))


def end_interrupted_runs(sweep_name: str, unfinished: list[str], experiment: str) -> None:
    """End the MLflow child run of each unfinished trial as KILLED, tagged `status=interrupted`; the
    restored sweep reopens it. Found by job name, not from the trial's results: a trial stopped
    before its first epoch report has a run but no run id in any result."""
    for trial_id in unfinished:
        run = find_job_run(f"{sweep_name}-{trial_id}", experiment)
        if run is not None:
            run.set_tags({"status": "interrupted"})
            run.end("KILLED")

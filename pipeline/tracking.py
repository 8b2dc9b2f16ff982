"""MLflow: one run per training job, named after the job, so a resumed job continues its run.

The tracking store is `MLFLOW_TRACKING_URI` when set, else the embedded `sqlite:///<cwd>/mlflow.db`
with artifacts in `<cwd>/mlartifacts` (set explicitly: MLflow's default would be relative to
whatever directory the process happens to run in). `mlflow ui --backend-store-uri sqlite:///mlflow.db`
shows the runs. The driver creates and ends runs; the rank-0 training worker logs into them by id.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from collections.abc import Iterator, Mapping
from pathlib import Path

from mlflow.entities import Metric, Param, RunStatus, RunTag
from mlflow.tracking import MlflowClient

from aniformer.cli import UserError

JOB_TAG = "aniformer.job"
DEFAULT_EXPERIMENT = "aniformer"
RUN_ID = re.compile(r"(?:runs:/)?([0-9a-f]{32})(?:/.*)?")  # a run id, or a runs:/ URI
CHECKPOINT_ARTIFACT = "checkpoints/best.pt"  # where jobs/train.py logs a run's best checkpoint


def tracking_uri() -> str:
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{Path.cwd() / 'mlflow.db'}"


def ui_hint(uri: str) -> str:
    """How to look at the runs of store `uri`: `mlflow ui` on an embedded store, else the server's own UI."""
    if uri.startswith(("http://", "https://")):
        return f"open {uri} in a browser"
    return f"mlflow ui --backend-store-uri {uri} --host 127.0.0.1"


def _artifact_location(uri: str) -> str | None:
    """Artifacts beside an embedded sqlite store; a tracking server decides for itself."""
    if uri.startswith("sqlite:///"):
        return (Path(uri.removeprefix("sqlite:///")).parent / "mlartifacts").resolve().as_uri()
    return None


def flatten(config: Mapping, prefix: str = "") -> dict[str, str]:
    """Nested config -> {"section.key": "value"} for MLflow params (lists as JSON)."""
    flat = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = json.dumps(value) if isinstance(value, (list, tuple)) else str(value)
    return flat


class Tracker:
    """A handle on one MLflow run by id; picklable, so Ray workers can log into the driver's run."""

    def __init__(self, uri: str, run_id: str):
        self.uri, self.run_id = uri, run_id

    @property
    def client(self) -> MlflowClient:
        return MlflowClient(self.uri)

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        import time
        now = int(time.time() * 1000)
        batch = [Metric(k, float(v), now, step) for k, v in metrics.items()]
        for i in range(0, len(batch), 500):
            self.client.log_batch(self.run_id, metrics=batch[i:i + 500])

    def log_artifact(self, path: str | os.PathLike, artifact_path: str | None = None) -> None:
        self.client.log_artifact(self.run_id, str(path), artifact_path)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        self.client.log_batch(self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])

    def end(self, status: str) -> None:
        self.client.set_terminated(self.run_id, status)

    @contextlib.contextmanager
    def ended(self) -> Iterator[None]:
        """End the run as the block leaves: FINISHED, KILLED on Ctrl-C or SIGTERM (SystemExit), else
        FAILED, so a job never leaves its run RUNNING."""
        status = "FAILED"
        try:
            yield
            status = "FINISHED"
        except (KeyboardInterrupt, SystemExit):
            status = "KILLED"
            raise
        finally:
            self.end(status)


def experiment_id(client: MlflowClient, name: str, uri: str) -> str:
    experiment = client.get_experiment_by_name(name)
    if experiment is not None:
        return experiment.experiment_id
    return client.create_experiment(name, artifact_location=_artifact_location(uri))


def _job_run_id(client: MlflowClient, exp_id: str, job: str) -> str | None:
    existing = client.search_runs([exp_id], filter_string=f"tags.`{JOB_TAG}` = '{job}'", max_results=1)
    return existing[0].info.run_id if existing else None


def find_job_run(job: str, experiment: str = DEFAULT_EXPERIMENT) -> Tracker | None:
    """The MLflow run of job `job` if one was started, else None."""
    uri = tracking_uri()
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    run_id = _job_run_id(client, exp.experiment_id, job) if exp is not None else None
    return Tracker(uri, run_id) if run_id else None


def start_job_run(job: str, config: Mapping, experiment: str = DEFAULT_EXPERIMENT,
                  parent_run_id: str | None = None) -> Tracker:
    """The MLflow run of job `job`: the existing one if the job ran before (resume), else a new one."""
    uri = tracking_uri()
    client = MlflowClient(uri)
    exp_id = experiment_id(client, experiment, uri)
    run_id = _job_run_id(client, exp_id, job)
    if run_id:
        client.update_run(run_id, status=RunStatus.to_string(RunStatus.RUNNING))
        return Tracker(uri, run_id)
    tags = {JOB_TAG: job}
    if parent_run_id:
        tags["mlflow.parentRunId"] = parent_run_id
    run = client.create_run(exp_id, run_name=job, tags=tags)
    params = [Param(k, v[:6000]) for k, v in flatten(config).items()]
    for i in range(0, len(params), 100):
        client.log_batch(run.info.run_id, params=params[i:i + 100])
    return Tracker(uri, run.info.run_id)


def quiet_mlflow() -> None:
    """MLflow (and alembic, creating a fresh sqlite store) log INFO lines to stderr: keep errors one line."""
    import logging

    import mlflow  # noqa: F401  (configures its loggers on import: set the level after it)

    for name in ("mlflow", "alembic"):
        logging.getLogger(name).setLevel(logging.WARNING)


def resolve_checkpoint(spec: str, scratch: Path) -> Path:
    """A checkpoint path from a file/directory, or an MLflow run id (downloads checkpoints/best.pt)."""
    path = Path(os.path.expanduser(spec))
    match = RUN_ID.fullmatch(spec)
    if path.exists() or match is None:
        if not path.exists():
            raise UserError(f"checkpoint not found: {spec} (give a checkpoint file or an MLflow run id)")
        return path
    quiet_mlflow()
    import mlflow

    uri = tracking_uri()
    try:
        local = mlflow.artifacts.download_artifacts(run_id=match.group(1), artifact_path=CHECKPOINT_ARTIFACT,
                                                    dst_path=str(scratch / match.group(1)), tracking_uri=uri)
    except Exception as e:  # unknown run, no such artifact, unreachable server: all one line
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise UserError(f"MLflow run {match.group(1)}: cannot download {CHECKPOINT_ARTIFACT} "
                        f"from {uri} ({first[:200]})") from None
    return Path(local)

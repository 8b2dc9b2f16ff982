"""MLflow: one run per job, so a resumed job continues its run.

A job's run is identified by its absolute output directory plus its name (tags `aniformer.out`, the
path, and `aniformer.out_id`, a digest of it that is safe in a search filter), never by the name alone:
two jobs of one name in different `--out`s get two runs, each with its own artifacts. A child run (a
sweep's trial) without an output of its own is identified by its parent run plus its name. The
output lock (`aniformer.cli.locks.lock_output`) makes the job the only one on its output, so a run of that
output still RUNNING when it starts was left so by a killed driver: it is ended KILLED (tagged
`aniformer.ended_by`), and the job's own run is then reopened.

The tracking store is `MLFLOW_TRACKING_URI` when set, else the embedded `sqlite:///<cwd>/mlflow.db`
with artifacts in `<cwd>/mlartifacts` (set explicitly: MLflow's default would be relative to
whatever directory the process happens to run in). `mlflow ui --backend-store-uri sqlite:///mlflow.db`
shows the runs. The driver creates and ends runs; the rank-0 training worker logs into them by id.
A fresh sqlite store is created (its tables migrated) by one process at a time (a file lock beside
it), so jobs started together on a new `mlflow.db` all succeed.

A tracking server (`MLFLOW_TRACKING_URI=http...`) is probed once per process before the first
client is made: one request to its `/health` with a `PROBE_TIMEOUT_S` timeout and no retries. One
that does not answer is a one-line error within seconds, instead of MLflow's own retries with
backoff (7 of them by default, minutes). Requests after the probe keep MLflow's retries: a server
that answered once and then hiccups is waited for.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

from mlflow.entities import Metric, Param, RunStatus, RunTag
from mlflow.tracking import MlflowClient

from aniformer.errors import UserError, root_cause

JOB_TAG = "aniformer.job"
OUT_TAG = "aniformer.out"  # the absolute output directory of the job
OUT_ID_TAG = "aniformer.out_id"  # sha256 of OUT_TAG (searchable whatever characters the path has)
PARENT_TAG = "mlflow.parentRunId"
DEFAULT_EXPERIMENT = "aniformer"
RUN_ID = re.compile(r"(?:runs:/)?([0-9a-f]{32})(?:/.*)?")  # a run id, or a runs:/ URI
CHECKPOINT_ARTIFACT = "checkpoints/best.pt"  # where jobs/train.py logs a run's best checkpoint


def tracking_uri() -> str:
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{Path.cwd() / 'mlflow.db'}"


_READY: set[str] = set()  # stores this process has opened (and so created, if they were new)
PROBE_TIMEOUT_S = 5  # to connect, and again to read the answer of the tracking server's /health


def require_reachable(uri: str) -> None:
    """`UserError` unless the tracking server of `uri` answers an HTTP request within
    `PROBE_TIMEOUT_S` (any status: behind authentication it answers 401). Other stores, and servers
    this process reached already, are not probed."""
    if uri in _READY or not uri.startswith(("http://", "https://")):
        return
    from mlflow.utils.credentials import get_default_host_creds
    from mlflow.utils.rest_utils import http_request

    try:  # MLflow's own request: its TLS and credential settings apply
        http_request(get_default_host_creds(uri), "/health", "GET", max_retries=0, timeout=PROBE_TIMEOUT_S,
                     raise_on_status=False)
    except Exception as e:  # refused, timed out, no such host, TLS: all one line
        raise UserError(f"MLflow tracking server {uri} does not answer ({_connection_error(e)}); start it, or unset "
                        "MLFLOW_TRACKING_URI to use ./mlflow.db") from None
    _READY.add(uri)


def _connection_error(error: BaseException) -> str:
    """The message of the root cause ("[Errno 111] Connection refused"), not of MLflow's, requests' and
    urllib3's wrappers around it."""
    root = root_cause(error)
    message = " ".join(str(root).split()) or type(root).__name__
    return message.rsplit(": ", 1)[-1][:200]  # urllib3 prefixes the connection object's repr


def client_for(uri: str) -> MlflowClient:
    """An MlflowClient of store `uri`. A tracking server is probed first (`require_reachable`). The
    first one of a process on a sqlite store is made under a file lock beside the database
    (`mlflow.db.lock`, removed after): opening a new store creates and migrates its tables, and two
    processes doing that at once break it ("Online migration expected to match one row")."""
    require_reachable(uri)
    if uri in _READY or not uri.startswith("sqlite:///"):
        return MlflowClient(uri)
    from aniformer.cli.locks import exclusive

    db = Path(uri.removeprefix("sqlite:///"))
    with exclusive(db.with_name(db.name + ".lock")):
        client = MlflowClient(uri)
    _READY.add(uri)
    return client


def output_id(out: str | os.PathLike) -> str:
    return hashlib.sha256(os.fsencode(os.path.abspath(out))).hexdigest()[:32]


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
        return client_for(self.uri)

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
        from aniformer.cli.exits import terminated

        status = "FAILED"
        try:
            yield
            status = "FINISHED"
        except (KeyboardInterrupt, SystemExit):
            status = "KILLED"
            raise
        finally:
            self.end("KILLED" if terminated() else status)


def experiment_id(client: MlflowClient, name: str, uri: str) -> str:
    experiment = client.get_experiment_by_name(name)
    if experiment is not None:
        return experiment.experiment_id
    from mlflow.exceptions import MlflowException

    try:
        return client.create_experiment(name, artifact_location=_artifact_location(uri))
    except MlflowException:  # another job created it just now
        experiment = client.get_experiment_by_name(name)
        if experiment is None:
            raise
        return experiment.experiment_id


def _search(client: MlflowClient, exp_id: str, filter_string: str) -> list:
    runs, token = [], None
    while True:
        page = client.search_runs([exp_id], filter_string=filter_string, max_results=1000, page_token=token)
        runs += list(page)
        token = page.token
        if not token:
            return runs


def _job_run(client: MlflowClient, exp_id: str, job: str, out: str | None = None,
             parent_run_id: str | None = None):
    """The run of job `job`: of output `out` if given, else the child of `parent_run_id` if given, else
    (callers that have neither) the newest run of that name that belongs to no output."""
    if out is not None:
        runs = _search(client, exp_id, f"tags.`{OUT_ID_TAG}` = '{output_id(out)}'")
        runs = [r for r in runs if r.data.tags.get(OUT_TAG) == os.path.abspath(out)]
    elif parent_run_id is not None:
        runs = _search(client, exp_id, f"tags.`{PARENT_TAG}` = '{parent_run_id}'")
    else:
        runs = [r for r in _search(client, exp_id, f"tags.`{JOB_TAG}` = '{job}'") if OUT_TAG not in r.data.tags]
    runs = [r for r in runs if r.data.tags.get(JOB_TAG) == job]
    return max(runs, key=lambda r: r.info.start_time or 0) if runs else None


def _job_run_id(client: MlflowClient, exp_id: str, job: str) -> str | None:
    run = _job_run(client, exp_id, job)
    return run.info.run_id if run else None


def find_job_run(job: str, experiment: str = DEFAULT_EXPERIMENT, *, out: str | os.PathLike | None = None,
                 parent_run_id: str | None = None) -> Tracker | None:
    """The MLflow run of job `job` (of output `out`, or child of `parent_run_id`; see `_job_run`) if
    one was started, else None."""
    uri = tracking_uri()
    client = client_for(uri)
    exp = client.get_experiment_by_name(experiment)
    run = _job_run(client, exp.experiment_id, job, out and os.path.abspath(out), parent_run_id) if exp else None
    return Tracker(uri, run.info.run_id) if run else None


def end_orphaned_runs(client: MlflowClient, exp_id: str, out: str) -> list[str]:
    """End KILLED every run still RUNNING of output `out` or of a directory inside it, and the children
    of those runs: the caller holds the lock on `out`, so no live job can be logging into them (their
    driver was killed). Returns their ids."""
    inside = out.rstrip("/") + "/"
    running = _search(client, exp_id, "attributes.status = 'RUNNING'")
    orphans = {r.info.run_id for r in running
               if r.data.tags.get(OUT_TAG) == out or r.data.tags.get(OUT_TAG, "").startswith(inside)}
    orphans |= {r.info.run_id for r in running if r.data.tags.get(PARENT_TAG) in orphans}
    note = (f"a job on {out} (pid {os.getpid()}, {time.strftime('%Y-%m-%d %H:%M:%S')}): the run's driver "
            "had died and left it RUNNING")
    for run_id in sorted(orphans):
        client.set_tag(run_id, "aniformer.ended_by", note)
        client.set_terminated(run_id, "KILLED")
    return sorted(orphans)


def start_job_run(job: str, config: Mapping, experiment: str = DEFAULT_EXPERIMENT,
                  parent_run_id: str | None = None, out: str | os.PathLike | None = None) -> Tracker:
    """The MLflow run of job `job` writing to output directory `out`: the existing one if this job ran
    before there (resume), else a new one. Without `out`, a child of `parent_run_id` is found by its
    parent and name, anything else by its name among the runs of no output (see `_job_run`).

    When this process holds the lock on `out`, runs of `out` left RUNNING by a killed driver are ended
    KILLED first (`end_orphaned_runs`)."""
    from aniformer.cli.locks import held_lock

    uri = tracking_uri()
    client = client_for(uri)
    exp_id = experiment_id(client, experiment, uri)
    out = os.path.abspath(out) if out is not None else None
    if out is not None and held_lock(out) is not None:
        end_orphaned_runs(client, exp_id, out)
    run = _job_run(client, exp_id, job, out, parent_run_id)
    if run is not None:
        client.update_run(run.info.run_id, status=RunStatus.to_string(RunStatus.RUNNING))
        return Tracker(uri, run.info.run_id)
    tags = {JOB_TAG: job}
    if out is not None:
        tags |= {OUT_TAG: out, OUT_ID_TAG: output_id(out)}
    if parent_run_id:
        tags[PARENT_TAG] = parent_run_id
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


def existing_store(what: str) -> str:
    """The tracking URI to read ``what`` from: a sqlite store that exists (never created by a lookup) or a
    server that answers; else `UserError`."""
    uri = tracking_uri()
    if uri.startswith("sqlite:///") and not Path(uri.removeprefix("sqlite:///")).is_file():
        raise UserError(f"{what}: there is no tracking store at {uri.removeprefix('sqlite:///')} "
                        "(set MLFLOW_TRACKING_URI, or run from the directory that holds mlflow.db)")
    require_reachable(uri)
    return uri


def download_run_checkpoint(run_id: str, scratch: Path) -> Path:
    """The best checkpoint (`CHECKPOINT_ARTIFACT`) of MLflow run `run_id`, downloaded into `scratch/RUN_ID`.
    A job's ``--checkpoint`` comes here through `pipeline.registry.resolve_checkpoint`."""
    quiet_mlflow()
    import mlflow

    uri = existing_store(f"MLflow run {run_id}")
    try:
        local = mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=CHECKPOINT_ARTIFACT,
                                                    dst_path=str(scratch / run_id), tracking_uri=uri)
    except Exception as e:  # unknown run, no such artifact, unreachable server: all one line
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise UserError(f"MLflow run {run_id}: cannot download {CHECKPOINT_ARTIFACT} "
                        f"from {uri} ({first[:200]})") from None
    return Path(local)

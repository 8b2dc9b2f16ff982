"""`python -m pipeline.mlflow_server` as cluster.yaml runs it, against real components.

- `--auth`: MLflow's basic-auth app answers 401 without (or with wrong) credentials and 200 with
  the admin user and the password from `--password-file`; a second server on the same store is
  refused; a user created there comes back from a directory backup into an empty store.
- `--backup s3://...`: moto's S3 server on 127.0.0.1 stands in for AWS. The first server creates the
  bucket private, keeps its artifacts in the bucket and backs its database up when stopped; a second
  server on an empty store restores the database from the bucket, with the run and its artifact.

Each server takes 10-25 s to start (database migrations), hence `slow`: the file runs in 45-90 s.
"""

from __future__ import annotations

import base64
import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
START_TIMEOUT = 120  # seconds for the wrapper to print its ready line (a shared 2-core machine)
STOP_TIMEOUT = 60  # the wrapper's own grace for its server is 30 s, then the backup
BUCKET = "aniformer-mlflow-test"
PASSWORD = "correct-horse-battery-staple-42"

pytestmark = pytest.mark.slow


def descendants(pid: int) -> set[int]:
    """pid's live process tree (the wrapper, the mlflow CLI, uvicorn and its workers)."""
    found, todo = set(), [pid]
    while todo:
        current = todo.pop()
        found.add(current)
        for task in Path(f"/proc/{current}/task").glob("*"):
            try:
                todo += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                pass
    return found


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


class Server:
    """One `python -m pipeline.mlflow_server` on 127.0.0.1, its output in a log file."""

    def __init__(self, tmp: Path, name: str, port: int, args: list[str], env: dict[str, str]):
        self.port = port
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = tmp / f"{name}.log"
        with open(self.log, "w") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "pipeline.mlflow_server", "--host", "127.0.0.1", "--port", str(self.port), *args],
                cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        self.tree: set[int] = set()

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_ready(self) -> None:
        deadline = time.time() + START_TIMEOUT
        while "MLflow tracking server: " not in self.output():
            assert self.proc.poll() is None, f"the server exited with {self.proc.returncode}:\n{self.output()[-3000:]}"
            assert time.time() < deadline, f"no ready line within {START_TIMEOUT} s:\n{self.output()[-3000:]}"
            time.sleep(0.5)
        self.tree = descendants(self.proc.pid)

    def stop(self) -> int:
        """SIGTERM to the wrapper, as systemd stops it on the head; its exit status."""
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGTERM)
        return self.proc.wait(timeout=STOP_TIMEOUT)

    def kill(self) -> None:
        """Cleanup after a failed test: whatever of the tree is still running."""
        for pid in self.tree | {self.proc.pid}:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
        self.proc.wait(timeout=STOP_TIMEOUT)


@pytest.fixture
def servers(tmp_path, free_ports):
    """Starts servers; stops (then kills) every one at the end, whatever the test did."""
    started: list[Server] = []

    def start(name: str, args: list[str], env: dict[str, str]) -> Server:
        server = Server(tmp_path, name, free_ports(1)[0], args, env)
        started.append(server)
        server.wait_ready()
        return server

    yield start
    for server in started:
        try:
            server.stop()
        finally:
            server.kill()


def clean_env(**extra: str) -> dict[str, str]:
    """This environment without any real AWS or MLflow client settings, plus `extra`."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("AWS_", "MLFLOW_"))}
    return {**env, **extra}


def status(url: str, user: str | None = None, password: str | None = None) -> int:
    request = urllib.request.Request(url)
    if user is not None:
        token = base64.b64encode(f"{user}:{password}".encode()).decode()
        request.add_header("Authorization", f"Basic {token}")
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status
    except urllib.error.HTTPError as e:
        return e.code


def request(url: str, user: str, password: str, body: dict | None = None) -> urllib.request.Request:
    req = urllib.request.Request(url, data=json.dumps(body).encode() if body is not None else None,
                                 headers={"Content-Type": "application/json"} if body is not None else {})
    req.add_header("Authorization", "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode())
    return req


def test_auth_answers_401_without_credentials_and_200_with_the_admin_password(tmp_path, servers, free_ports):
    """Also: one server per store (a second is refused at once), and with --backup the users' database
    is backed up and restored beside the runs' one."""
    password_file = tmp_path / "auth_token"
    password_file.write_text(PASSWORD + "\n")  # `ray get-auth-token --generate` ends its file with a newline
    args = ["--auth", "--password-file", str(password_file), "--backup", str(tmp_path / "backup")]
    env = clean_env(MLFLOW_TRACKING_USERNAME="admin")
    server = servers("auth", ["--store", str(tmp_path / "store"), *args], env)
    search = f"{server.url}/api/2.0/mlflow/experiments/search?max_results=10"

    assert status(search) == 401
    assert status(search, "admin", "not-the-password-at-all") == 401
    assert status(search, "someone", PASSWORD) == 401
    assert status(search, "admin", PASSWORD) == 200
    assert status(f"{server.url}/health") == 200  # the wrapper's readiness probe sends no credentials

    second = subprocess.run([sys.executable, "-m", "pipeline.mlflow_server", "--host", "127.0.0.1", "--port",
                             str(free_ports(1)[0]), "--store", str(tmp_path / "store")], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=60)
    lines = second.stderr.strip().splitlines()
    assert second.returncode == 2 and len(lines) == 1, second.stderr[-3000:]
    assert lines[0].startswith(f"error: --store {tmp_path / 'store'} is in use by another job (pid {server.proc.pid} ")

    with urllib.request.urlopen(request(f"{server.url}/api/2.0/mlflow/users/create", "admin", PASSWORD,
                                        {"username": "ana", "password": "a-user-password-of-ana"}), timeout=10) as r:
        assert r.status == 200
    assert status(search, "ana", "a-user-password-of-ana") == 200
    assert server.stop() == 0, server.output()[-3000:]
    assert not [pid for pid in server.tree if alive(pid)], "the server left processes behind"
    assert f"backed up {tmp_path / 'store' / 'basic_auth.db'} to {tmp_path / 'backup'}/basic_auth.db" in server.output()

    restored = servers("restored", ["--store", str(tmp_path / "empty"), *args], env)
    assert f"restored {tmp_path / 'empty' / 'basic_auth.db'} from {tmp_path / 'backup'}/basic_auth.db" in restored.output()
    search = f"{restored.url}/api/2.0/mlflow/experiments/search?max_results=10"
    assert status(search, "ana", "a-user-password-of-ana") == 200  # the user came back with the store
    assert status(search, "ana", "not-her-password-at-all") == 401


@pytest.fixture
def s3():
    """moto's S3 server on 127.0.0.1: the servers' environment for it, and a boto3 client of it."""
    import boto3
    from moto.server import ThreadedMotoServer

    moto = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    moto.start()
    host, port = moto.get_host_and_port()
    env = {"AWS_ENDPOINT_URL": f"http://{host}:{port}", "MLFLOW_S3_ENDPOINT_URL": f"http://{host}:{port}",
           "AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
           "AWS_DEFAULT_REGION": "us-west-2"}  # not us-east-1: bucket creation then needs a LocationConstraint
    try:
        yield env, boto3.client("s3", endpoint_url=env["AWS_ENDPOINT_URL"], region_name=env["AWS_DEFAULT_REGION"],
                                aws_access_key_id="testing", aws_secret_access_key="testing")
    finally:
        moto.stop()


def keys(client, prefix: str) -> list[str]:
    listing = client.list_objects_v2(Bucket=BUCKET, Prefix=prefix)
    return [obj["Key"] for obj in listing.get("Contents", [])]


def test_s3_backup_on_stop_restores_runs_and_artifacts_into_an_empty_store(tmp_path, servers, s3, monkeypatch):
    from mlflow import MlflowClient

    env, bucket = s3
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")  # a failing call fails now, not after minutes
    backup = ["--backup", f"s3://{BUCKET}/mlflow", "--create-bucket", "--backup-every", "3600"]  # only the one on stop
    first = servers("first", ["--store", str(tmp_path / "first"), *backup], clean_env(**env))

    blocked = bucket.get_public_access_block(Bucket=BUCKET)["PublicAccessBlockConfiguration"]
    assert blocked == {"BlockPublicAcls": True, "IgnorePublicAcls": True, "BlockPublicPolicy": True,
                       "RestrictPublicBuckets": True}
    client = MlflowClient(tracking_uri=first.url)
    run = client.create_run(client.create_experiment("backed-up"), run_name="tiny")
    client.log_metric(run.info.run_id, "pmd_unseen", 0.125)
    client.log_text(run.info.run_id, "seen through the tracking server", "notes/readme.txt")
    client.set_terminated(run.info.run_id)
    artifact_keys = keys(bucket, "mlflow/artifacts/")
    assert [k for k in artifact_keys if k.endswith(f"{run.info.run_id}/artifacts/notes/readme.txt")], artifact_keys
    assert not keys(bucket, "mlflow/mlflow.db"), "a backup before the stop: --backup-every was not honoured"

    assert first.stop() == 0, first.output()[-3000:]
    assert not [pid for pid in first.tree if alive(pid)], "the server left processes behind"
    assert keys(bucket, "mlflow/mlflow.db") == ["mlflow/mlflow.db"], first.output()[-3000:]
    assert f"backed up {tmp_path / 'first' / 'mlflow.db'} to s3://{BUCKET}/mlflow/mlflow.db" in first.output()

    second = servers("second", ["--store", str(tmp_path / "second"), *backup], clean_env(**env))
    assert f"restored {tmp_path / 'second' / 'mlflow.db'} from s3://{BUCKET}/mlflow/mlflow.db" in second.output()
    client = MlflowClient(tracking_uri=second.url)
    restored = client.get_run(run.info.run_id)
    assert (restored.info.run_name, restored.info.status) == ("tiny", "FINISHED")
    assert restored.data.metrics == {"pmd_unseen": 0.125}
    download = Path(client.download_artifacts(run.info.run_id, "notes/readme.txt", str(tmp_path)))
    assert download.read_text() == "seen through the tracking server"

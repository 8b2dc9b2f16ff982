"""The MLflow tracking server of a cluster (or of one machine): one address, a durable store.

    python -m pipeline.mlflow_server --host 127.0.0.1 --port 5000 --store ~/mlflow
    python -m pipeline.mlflow_server --host 10.0.1.23 --port 5000 --store ~/mlflow \\
        --backup s3://aniformer-mlflow-123456789012-us-west-2/mlflow --auth        # what cluster.yaml runs

- Backend store: SQLite `STORE/mlflow.db`, served by one server at a time (a lock file in STORE: a
  second server on the same store is refused in one line; two used to race the first migration and
  break the store for good). With `--backup DEST` (an `s3://bucket/prefix` or a directory), a
  missing local database is restored from `DEST/` at start, and a consistent copy (SQLite's online
  backup API, safe while the server writes) goes to DEST every `--backup-every` seconds and when
  the server is stopped (SIGTERM/SIGINT). With `--auth`, the users' database `basic_auth.db` is
  restored and backed up the same way.
- Artifacts: `--artifacts` (default `DEST/artifacts` for an s3:// backup, else `STORE/artifacts`),
  served through the tracking server (`--serve-artifacts`), so clients need no S3 credentials.
- `--host` must name one address: 0.0.0.0 and :: are refused unless `--allow-all-interfaces`.
  MLflow's own middleware additionally refuses Host headers other than localhost / private IPs.
- `--auth`: MLflow's basic-auth app (needs `mlflow[auth]`); the admin user is
  `MLFLOW_TRACKING_USERNAME` (default `admin`) with the password in `--password-file` (else
  `MLFLOW_TRACKING_PASSWORD`); clients send the same two variables. On the cluster the password
  file is Ray's auth token: whoever holds it can already run code on the cluster.

MLflow's background job runner (GenAI evaluation jobs, unused here) is switched off: it starts
half a dozen worker processes.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import secrets
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

from aniformer.cli.args import ArgumentParser
from aniformer.cli.exits import run
from aniformer.cli.locks import lock_output, releases_locks
from aniformer.errors import UserError
from aniformer.io.files import atomic_path

DB = "mlflow.db"
AUTH_DB = "basic_auth.db"  # MLflow's basic-auth users and permissions
WILDCARDS = {"0.0.0.0", "::", ""}


def check_host(host: str, allow_all: bool) -> str:
    """The bind address; a wildcard only when explicitly allowed (the server has no auth by default)."""
    if host.strip("[]") in WILDCARDS and not allow_all:
        raise UserError(f"--host {host!r} listens on every interface; name one address (127.0.0.1, the "
                        "node's private IP) or pass --allow-all-interfaces")
    if host != "localhost":
        try:
            ipaddress.ip_address(host.strip("[]"))
        except ValueError:
            raise UserError(f"--host {host!r} is not an IP address") from None
    return host


def server_command(host: str, port: int, store: Path, artifacts: str, auth: bool) -> list[str]:
    """The `mlflow server` command line (the mlflow next to this Python)."""
    mlflow = Path(sys.executable).with_name("mlflow")
    cmd = [str(mlflow) if mlflow.exists() else "mlflow", "server", "--host", host, "--port", str(port),
           "--backend-store-uri", f"sqlite:///{store / DB}", "--serve-artifacts",
           "--artifacts-destination", artifacts, "--workers", "1"]
    return cmd + (["--app-name", "basic-auth"] if auth else [])


# ------------------------------------------------------------------ backup destination: s3:// or a directory


def _s3(dest: str):
    import boto3  # only the cluster's head needs it (cluster.yaml installs it there)

    bucket, _, prefix = dest.removeprefix("s3://").partition("/")
    return boto3.client("s3"), bucket, prefix.strip("/")


def ensure_bucket(dest: str) -> None:
    """Create the backup bucket if missing, private (all public access blocked)."""
    if not dest.startswith("s3://"):
        return
    client, bucket, _ = _s3(dest)
    try:
        client.head_bucket(Bucket=bucket)
        return
    except client.exceptions.ClientError:
        pass
    region = client.meta.region_name
    kwargs = {} if region in (None, "us-east-1") else {"CreateBucketConfiguration": {"LocationConstraint": region}}
    client.create_bucket(Bucket=bucket, **kwargs)
    client.put_public_access_block(Bucket=bucket, PublicAccessBlockConfiguration={
        "BlockPublicAcls": True, "IgnorePublicAcls": True, "BlockPublicPolicy": True, "RestrictPublicBuckets": True})


def fetch(dest: str, name: str, local: Path) -> bool:
    """Copy DEST/name to `local`; False if there is none."""
    if dest.startswith("s3://"):
        client, bucket, prefix = _s3(dest)
        try:
            client.download_file(bucket, f"{prefix}/{name}".lstrip("/"), str(local))
            return True
        except client.exceptions.ClientError:
            return False
    source = Path(dest) / name
    if not source.is_file():
        return False
    with atomic_path(local) as tmp:  # a restore cut short leaves no partial database that looks complete
        tmp.write_bytes(source.read_bytes())
    return True


def push(local: Path, dest: str, name: str) -> None:
    if dest.startswith("s3://"):
        client, bucket, prefix = _s3(dest)
        client.upload_file(str(local), bucket, f"{prefix}/{name}".lstrip("/"))
        return
    with atomic_path(Path(dest) / name) as tmp:
        tmp.write_bytes(local.read_bytes())


def backup(store: Path, dest: str) -> list[str]:
    """Consistent snapshots of the store's databases (online backup API), copied to DEST; their names."""
    done = []
    for name in (DB, AUTH_DB):
        source = store / name
        if not source.is_file():
            continue
        with tempfile.TemporaryDirectory(dir=store) as scratch:
            snapshot = Path(scratch) / name
            src, dst = sqlite3.connect(source), sqlite3.connect(snapshot)
            try:
                src.backup(dst)
            finally:
                dst.close()
                src.close()
            push(snapshot, dest, name)
        done.append(name)
    return done


def restore(store: Path, dest: str, auth: bool) -> None:
    """Fetch the databases the store lacks from DEST (the users' one only for an --auth server)."""
    for name in (DB, AUTH_DB) if auth else (DB,):
        if not (store / name).exists() and fetch(dest, name, store / name):
            print(f"restored {store / name} from {dest}/{name}", flush=True)


# ------------------------------------------------------------------ the server process


def _auth_env(store: Path, password_file: str | None) -> dict[str, str]:
    if password_file:
        try:
            password = Path(password_file).expanduser().read_text().strip()
        except OSError as e:
            raise UserError(f"--password-file {password_file}: {e.strerror}") from None
    else:
        password = os.environ.get("MLFLOW_TRACKING_PASSWORD", "")
    if len(password) < 16:
        raise UserError("--auth needs a password of >= 16 characters (--password-file or MLFLOW_TRACKING_PASSWORD)")
    try:
        import flask_wtf  # noqa: F401
    except ImportError:
        raise UserError("--auth needs MLflow's auth extra: pip install 'mlflow[auth]'") from None
    ini = store / "basic_auth.ini"
    ini.write_text("[mlflow]\ndefault_permission = NO_PERMISSIONS\n"
                   f"database_uri = sqlite:///{store / AUTH_DB}\n"
                   f"admin_username = {os.environ.get('MLFLOW_TRACKING_USERNAME', 'admin')}\n"
                   "authorization_function = mlflow.server.auth:authenticate_request_basic_auth\n")
    key = store / "flask_secret_key"
    if not key.is_file():
        key.touch(mode=0o600)
        key.write_text(secrets.token_hex(32))
    return {"MLFLOW_AUTH_CONFIG_PATH": str(ini), "MLFLOW_AUTH_ADMIN_PASSWORD": password,
            "MLFLOW_FLASK_SERVER_SECRET_KEY": key.read_text().strip()}


def wait_healthy(url: str, proc: subprocess.Popen, timeout: float, stopping: threading.Event) -> None:
    deadline = time.time() + timeout
    while not stopping.is_set():
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=5) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        if proc.poll() is not None:
            raise UserError(f"mlflow server exited with status {proc.returncode} (see its output above)")
        if time.time() > deadline:
            raise UserError(f"mlflow server did not answer {url}/health within {timeout:.0f} s")
        time.sleep(1)


def stop(proc: subprocess.Popen, grace: float = 30) -> None:
    """Stop the server and everything it started (its own process group)."""
    if proc.poll() is not None:
        return
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = ArgumentParser(prog="mlflow_server.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--host", default="127.0.0.1", help="one address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=5000)
    p.add_argument("--store", required=True, metavar="DIR", help="directory of mlflow.db (and auth files)")
    p.add_argument("--artifacts", metavar="URI", help="artifact destination (default: BACKUP/artifacts or STORE/artifacts)")
    p.add_argument("--backup", metavar="DEST", help="s3://bucket/prefix or a directory: restore from / back up to")
    p.add_argument("--backup-every", type=float, default=300, metavar="S", help="seconds between backups (default 300)")
    p.add_argument("--create-bucket", action="store_true", help="create the s3:// backup bucket if missing (private)")
    p.add_argument("--auth", action="store_true", help="MLflow basic auth (admin: MLFLOW_TRACKING_USERNAME, default admin)")
    p.add_argument("--password-file", metavar="FILE", help="the admin password (default: MLFLOW_TRACKING_PASSWORD)")
    p.add_argument("--allow-all-interfaces", action="store_true", help="permit --host 0.0.0.0 / ::")
    p.add_argument("--start-timeout", type=float, default=180, metavar="S")
    return p.parse_args(argv)


@releases_locks
def main(argv: list[str]) -> None:
    args = parse_args(argv)
    host = check_host(args.host, args.allow_all_interfaces)
    store = Path(args.store).expanduser().resolve()
    lock_output(store, "--store")  # one server per store
    dest = args.backup.rstrip("/") if args.backup else None
    if dest and not dest.startswith("s3://"):
        dest = str(Path(dest).expanduser().resolve())
    if dest:
        if args.create_bucket:
            ensure_bucket(dest)
        restore(store, dest, args.auth)
    artifacts = args.artifacts or (f"{dest}/artifacts" if dest and dest.startswith("s3://") else str(store / "artifacts"))
    env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    if args.auth:
        env.update(_auth_env(store, args.password_file))
    url = f"http://{host if ':' not in host else f'[{host}]'}:{args.port}"
    proc = subprocess.Popen(server_command(host, args.port, store, artifacts, args.auth), env=env, cwd=store,
                            start_new_session=True)
    stopping = threading.Event()

    def on_signal(*_):
        stopping.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        wait_healthy(url, proc, args.start_timeout, stopping)
        print(f"MLflow tracking server: {url} (store {store / DB}, artifacts {artifacts}"
              + (f", backups to {dest} every {args.backup_every:.0f} s" if dest else "") + ")", flush=True)
        last = time.time()
        while not stopping.wait(1):
            if proc.poll() is not None:
                raise UserError(f"mlflow server exited with status {proc.returncode}")
            if dest and time.time() - last >= args.backup_every:
                backup(store, dest)
                last = time.time()
    finally:
        stop(proc)
        if dest:
            for name in backup(store, dest):
                print(f"backed up {store / name} to {dest}/{name}", flush=True)


if __name__ == "__main__":
    run(main)

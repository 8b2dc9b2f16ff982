"""A real `ray start --head` (bound to 127.0.0.1) and `ray job submit` of the tiny training job.

Runs beside the session cluster on its own ports and temp dir; the head is started with `--block`
and stopped through its own pid, never with `ray stop` (which would kill every Ray on the machine).
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listening_addresses(port: int) -> set[str]:
    """Local addresses with a TCP socket listening on `port` (from /proc/net/tcp)."""
    found = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        address, hex_port = local.split(":")
        if state == "0A" and int(hex_port, 16) == port:  # 0A = LISTEN
            found.add(socket.inet_ntoa(bytes.fromhex(address)[::-1]))
    return found


def test_ray_start_head_and_job_submit_of_the_training_job(tmp_path, repo_root):
    bin_dir = Path(sys.executable).parent
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["PATH"] = f"{bin_dir}:{env['PATH']}"  # the job's `python` must be this venv's
    # Token authentication, as docs/cluster.md recommends: the job API runs code for whoever reaches it.
    env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(32))
    gcs_port, dashboard_port = free_port(), free_port()
    temp_dir = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # short: Ray's socket paths have a length limit
    head = subprocess.Popen(
        [str(bin_dir / "ray"), "start", "--head", "--block", "--node-ip-address=127.0.0.1", f"--port={gcs_port}",
         "--dashboard-host=127.0.0.1", f"--dashboard-port={dashboard_port}", "--num-cpus=2",
         f"--temp-dir={temp_dir}", "--include-dashboard=true"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    address = f"http://127.0.0.1:{dashboard_port}"
    try:
        deadline = time.time() + 120
        while subprocess.run([str(bin_dir / "ray"), "job", "list", "--address", address], env=env,
                             capture_output=True).returncode != 0:
            assert head.poll() is None, "ray start --head exited"
            assert time.time() < deadline, "the job server did not come up"
            time.sleep(2)
        assert listening_addresses(dashboard_port) == {"127.0.0.1"}  # not 0.0.0.0
        intruder = subprocess.run([str(bin_dir / "ray"), "job", "list", "--address", address],
                                  env={**env, "RAY_AUTH_TOKEN": "0" * 64}, capture_output=True, text=True)
        assert intruder.returncode != 0 and "token" in intruder.stderr.lower()

        out = tmp_path / "run"
        runtime_env = {"env_vars": {"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}}
        for _ in range(30):  # the head's job agent registers a little after the dashboard answers
            submit = subprocess.run(
                [str(bin_dir / "ray"), "job", "submit", "--address", address, "--working-dir", str(repo_root),
                 "--runtime-env-json", json.dumps(runtime_env), "--",
                 "python", "jobs/train.py", "--config", "configs/tiny.yaml", "--out", str(out)],
                env=env, capture_output=True, text=True, timeout=900)
            if "No available agent to submit job" not in submit.stdout + submit.stderr:
                break
            time.sleep(2)
        assert "succeeded" in submit.stdout, submit.stdout[-3000:] + submit.stderr[-2000:]
        assert (out / "best.pt").is_file() and (tmp_path / "mlflow.db").is_file()
    finally:
        os.killpg(head.pid, signal.SIGTERM)  # --block tears down the processes it started
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
        shutil.rmtree(temp_dir, ignore_errors=True)

"""The system tests' machinery: a real local Ray cluster started the way cluster.yaml starts one, jobs
submitted to it with `ray job submit`, tracked by our MLflow server, and what listens where (/proc).

`started_cluster` (the session's `cluster` fixture, tests/conftest.py) starts, in processes of its own:

- an MLflow tracking server (`python -m pipeline.mlflow_server`, what the cluster's head runs) on
  127.0.0.1 with its store and a backup directory;
- `ray start --head --block` bound to 127.0.0.1 with token authentication, and two worker nodes
  (`ray start --address=... --block`), each in its own process group and temp dir, every port
  chosen free (two Ray instances on one machine otherwise collide, e.g. on the dashboard agent's
  52365 or the autoscaler's and the dashboard's metrics ports 44217 and 44227);
- every node started with MLFLOW_TRACKING_URI in its environment, as cluster.yaml does, so jobs log
  to the server without being told (no runtime_env).

`run_jobs` (the session's `jobs` fixture) submits the tiny training job and, as soon as its mesh bank
exists, a tiny sweep (both run at once), and waits for both. Everything is stopped through its own
process group, never with `ray stop` (which would kill every Ray on the machine).

Used by tests/test_cluster_jobs.py, test_cluster_mlflow_ui.py, test_cluster_security.py and test_local_ray.py.
"""

from __future__ import annotations

import contextlib
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
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
OBJECT_STORE = str(256 * 1024**2)
TRAIN = ["train.epochs=1", "data.workers=2"]  # 2 generation tasks: the machine has 2 cores
# Up to two trials at once, spread over the nodes: a trial holds 0.05 + 0.5 CPU and its Ray Data reads
# 1 more (docs/sweeps.md); the cluster has 4 logical CPUs (head 2, workers 1 each; 2 physical cores),
# and the training job holds 1.5 of them while it runs beside the sweep.
# Two trials, given far apart, so that the compare view's plots (test_mlflow_compare_view_...) have
# lambdas and windows that differ; tests/test_sweep.py covers the search's own draws.
SWEEP = ["sweep.num_samples=2", "sweep.search=random", "sweep.max_concurrent=2", "sweep.memory_limit_gb=16",
         "sweep.points=[{rec: 0.3, motion: 1.0e-4, appearance: 3.0e-3, window: 2}, "
         "{rec: 3.0, motion: 3.0e-3, appearance: 1.0e-4, window: 6}]",
         "train.epochs=1", "train.render_every=1"]
TRIALS = 2


# ------------------------------------------------------------------ who listens where (/proc)


def group_pids(pgid: int) -> set[int]:
    pids = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == pgid:
                pids.add(int(entry.name))
    return pids


def kill_group(pgid: int) -> None:
    """SIGKILL what is left of a process group; members may exit while we go through them."""
    for pid in group_pids(pgid):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def tree_pids(root: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except OSError:
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    pids, todo = set(), [root]
    while todo:
        pid = todo.pop()
        pids.add(pid)
        todo += children.get(pid, [])
    return pids


def _address(hex_address: str) -> str:
    raw = bytes.fromhex(hex_address)
    if len(raw) == 4:
        return socket.inet_ntop(socket.AF_INET, raw[::-1])
    return socket.inet_ntop(socket.AF_INET6, b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4)))


def listening_sockets(pids: set[int]) -> dict[tuple[str, int], int]:
    """{(address, port): pid} of the TCP sockets in LISTEN state held by the given processes."""
    inodes = {}
    for pid in pids:
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                try:
                    target = os.readlink(fd)
                except OSError:
                    continue
                if target.startswith("socket:["):
                    inodes[target[8:-1]] = pid
        except OSError:
            continue
    found = {}
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # 0A = LISTEN
                address, port = fields[1].split(":")
                found[(_address(address), int(port, 16))] = inodes[fields[9]]
    return found


def listeners(pids: set[int]) -> set[tuple[str, int]]:
    return set(listening_sockets(pids))


def command(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:200]
    except OSError:
        return "?"


def addresses(port: int, pids: set[int]) -> set[str]:
    return {a.removeprefix("::ffff:") for a, p in listeners(pids) if p == port}


WILDCARD = {"0.0.0.0", "::"}
WORKER_PORTS = range(10002, 20000)  # Ray's default --min-worker-port/--max-worker-port; the free_ports fixture stays above


# ------------------------------------------------------------------ the cluster


@dataclass
class Cluster:
    root: Path
    env: dict
    dashboard: str
    gcs: str
    mlflow: str
    mlflow_port: int
    dashboard_port: int
    ray_rpc_ports: set[int]  # Ray's token-authenticated RPC ports (all interfaces by Ray's design)
    metrics_ports: set[int]  # Ray's Prometheus exporters (all interfaces; read-only metrics)
    # Ray's worker processes (actors, tasks, the dashboard agent's core worker) serve their RPC on a port
    # of this range, on all interfaces; every node is given it (Ray's default, made explicit)
    worker_ports: range = WORKER_PORTS
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    jobs: dict[str, str] = field(default_factory=dict)  # test name -> Ray job submission id
    logs: dict[str, Path] = field(default_factory=dict)
    commands: dict[str, list[str]] = field(default_factory=dict)  # how each of `procs` was started

    def ray(self, *args: str, env: dict | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
        return subprocess.run([str(BIN / "ray"), *args], env=env or self.env, capture_output=True, text=True,
                              timeout=timeout)

    def tail(self, name: str, n: int = 3000) -> str:
        return self.logs[name].read_text(errors="replace")[-n:] if name in self.logs else ""

    def pids(self) -> set[int]:
        """Every process we started: each node's process group, and the MLflow wrapper's descendants
        (it runs `mlflow server` in a process group of its own)."""
        alive = [p.pid for p in self.procs.values() if p.poll() is None]
        return set().union(*(group_pids(pid) | tree_pids(pid) for pid in alive))

    def alive_nodes(self) -> int:
        request = urllib.request.Request(f"{self.dashboard}/api/v0/nodes?limit=100",
                                         headers={"Authorization": f"Bearer {self.env['RAY_AUTH_TOKEN']}"})
        try:
            with urllib.request.urlopen(request, timeout=20) as r:
                nodes = json.loads(r.read())["data"]["result"]["result"]
        except (OSError, KeyError, ValueError):
            return 0
        return sum(1 for n in nodes if n.get("state") == "ALIVE")


def start(cluster: Cluster, name: str, cmd: list[str], **env: str) -> None:
    log = cluster.root / f"{name}.log"
    if log.exists():  # a restart: keep the earlier log beside the new one
        log.rename(log.with_suffix(f".{time.time():.0f}.log"))
    cluster.logs[name] = log
    cluster.commands[name] = cmd
    with open(log, "w") as f:
        cluster.procs[name] = subprocess.Popen(cmd, env={**cluster.env, **env}, cwd=ROOT, stdout=f,
                                               stderr=subprocess.STDOUT, start_new_session=True)


def stop(procs: list[subprocess.Popen], grace: float = 10) -> None:
    """SIGTERM each process group (`ray start --block` tears its node down; our MLflow wrapper stops
    its server), then SIGKILL whatever is left after `grace` seconds."""
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    deadline = time.time() + grace
    for p in procs:
        try:
            p.wait(timeout=max(1, deadline - time.time()))
        except subprocess.TimeoutExpired:
            pass
        kill_group(p.pid)
        if p.poll() is None:
            p.wait(timeout=30)


def wait_for(what: str, ok, cluster: Cluster, timeout: float = 240, every: float = 2, tolerate=()):
    deadline = time.time() + timeout
    while True:
        result = ok()
        if result:
            return result
        dead = [n for n, p in cluster.procs.items() if p.poll() is not None and n not in tolerate]
        assert not dead, f"{', '.join(dead)} exited while waiting for {what}:\n" + "\n".join(cluster.tail(n) for n in dead)
        assert time.time() < deadline, f"timed out waiting for {what}"
        time.sleep(every)


def healthy(url: str) -> bool:
    try:
        with urllib.request.urlopen(f"{url}/health", timeout=5) as r:
            return r.status == 200
    except OSError:
        return False


@contextlib.contextmanager
def started_cluster(root: Path, free_ports):
    """The cluster, started in `root` (its logs, the MLflow store and its backup, the jobs' --out) on
    ports `free_ports(n)` gives; stopped, and its nodes' raylet logs copied into `root`, on exit."""
    (gcs, dashboard, client, head_agent, head_agent_grpc, head_metrics, head_runtime_env, head_nm, head_om,
     autoscaler_metrics, dashboard_metrics, mlflow_port, *worker_ports) = free_ports(12 + 2 * 6)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("RAY_", "MLFLOW_"))}
    env["PATH"] = f"{BIN}:{env['PATH']}"  # the job's `python` must be this venv's
    # Token authentication, as on the cluster: the job API runs code for whoever reaches it.
    env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(32), RAY_DEDUP_LOGS="0",
               MLFLOW_TRACKING_URI=f"http://127.0.0.1:{mlflow_port}")
    # One temp dir per node, short (Ray's socket paths have a length limit): nodes started at the same
    # moment in one temp dir race for the same socket names ("bind: Address already in use").
    temp_dirs = [tempfile.mkdtemp(prefix="ray", dir="/tmp") for _ in range(3)]
    c = Cluster(root=root, env=env, dashboard=f"http://127.0.0.1:{dashboard}", gcs=f"127.0.0.1:{gcs}",
                mlflow=f"http://127.0.0.1:{mlflow_port}", mlflow_port=mlflow_port, dashboard_port=dashboard,
                ray_rpc_ports={gcs, head_agent_grpc, head_nm, head_om},
                metrics_ports={head_metrics, autoscaler_metrics, dashboard_metrics})
    try:
        start(c, "mlflow", [sys.executable, "-m", "pipeline.mlflow_server", "--host", "127.0.0.1",
                            "--port", str(mlflow_port), "--store", str(root / "mlflow"),
                            "--backup", str(root / "mlflow-backup"), "--backup-every", "3600"])
        common = ["--block", "--node-ip-address=127.0.0.1", f"--object-store-memory={OBJECT_STORE}",
                  f"--min-worker-port={WORKER_PORTS.start}", f"--max-worker-port={WORKER_PORTS.stop - 1}"]
        start(c, "head", [str(BIN / "ray"), "start", "--head", *common, "--num-cpus=2", f"--temp-dir={temp_dirs[0]}",
                          f"--port={gcs}",
                          "--include-dashboard=true", "--dashboard-host=127.0.0.1", f"--dashboard-port={dashboard}",
                          f"--ray-client-server-port={client}", f"--dashboard-agent-listen-port={head_agent}",
                          f"--dashboard-agent-grpc-port={head_agent_grpc}", f"--metrics-export-port={head_metrics}",
                          f"--runtime-env-agent-port={head_runtime_env}", f"--node-manager-port={head_nm}",
                          f"--object-manager-port={head_om}"],
              # fixed 44217 and 44227 otherwise: one per machine, taken by whichever Ray starts first
              AUTOSCALER_METRIC_PORT=str(autoscaler_metrics), DASHBOARD_METRIC_PORT=str(dashboard_metrics))
        wait_for("the head", lambda: c.alive_nodes() == 1, c)  # workers join a head that is fully up
        workers = {}
        for i in range(2):
            agent, agent_grpc, metrics, runtime_env, nm, om = worker_ports[6 * i:6 * i + 6]
            c.ray_rpc_ports |= {agent_grpc, nm, om}
            c.metrics_ports.add(metrics)
            workers[f"worker{i}"] = [str(BIN / "ray"), "start", f"--address={c.gcs}", *common, "--num-cpus=1",
                                     f"--temp-dir={temp_dirs[i + 1]}",
                                     f"--dashboard-agent-listen-port={agent}", f"--dashboard-agent-grpc-port={agent_grpc}",
                                     f"--metrics-export-port={metrics}", f"--runtime-env-agent-port={runtime_env}",
                                     f"--node-manager-port={nm}", f"--object-manager-port={om}"]
            start(c, f"worker{i}", workers[f"worker{i}"])

        def joined() -> bool:
            # `ray start` gives a raylet 30 s to register (hard-coded in Ray 2.60): on a loaded 2-core
            # machine that can pass. Such a worker exits; clear its process group and start it again.
            for name, cmd in workers.items():
                proc = c.procs[name]
                if proc.poll() is not None:
                    assert "timed out during startup" in c.tail(name), f"{name} exited:\n{c.tail(name)}"
                    stop([proc], grace=5)
                    start(c, name, cmd)
            return c.alive_nodes() == 3

        wait_for("three alive nodes", joined, c, timeout=400, tolerate=set(workers))
        wait_for("the MLflow server", lambda: healthy(c.mlflow), c)
        yield c
    finally:
        stop([c.procs[n] for n in ("worker0", "worker1", "head", "mlflow") if n in c.procs])
        for i, temp_dir in enumerate(temp_dirs):  # keep the nodes' own logs beside the test's
            for log in Path(temp_dir).glob("session_*/logs/raylet*"):
                (root / f"node{i}-logs").mkdir(exist_ok=True)
                shutil.copyfile(log, root / f"node{i}-logs" / log.name)
            shutil.rmtree(temp_dir, ignore_errors=True)


# ------------------------------------------------------------------ jobs submitted to it, and their runs


def submit(c: Cluster, name: str, *entrypoint: str) -> str:
    """`ray job submit --no-wait` of this checkout (retried while the head's job agent registers); the job id."""
    job_id = f"{name}-{secrets.token_hex(4)}"
    for _ in range(30):
        job = c.ray("job", "submit", "--address", c.dashboard, "--working-dir", str(ROOT), "--submission-id", job_id,
                    "--no-wait", "--", *entrypoint)
        if job.returncode == 0:
            c.jobs[name] = job_id
            return job_id
        assert "No available agent to submit job" in job.stdout + job.stderr, job.stdout[-2000:] + job.stderr[-2000:]
        time.sleep(2)
    raise AssertionError(f"the job agent never came up: {job.stderr[-2000:]}")


def jobs_api(c: Cluster, path: str) -> dict:
    request = urllib.request.Request(f"{c.dashboard}/api/jobs/{path}",
                                     headers={"Authorization": f"Bearer {c.env['RAY_AUTH_TOKEN']}"})
    with urllib.request.urlopen(request, timeout=30) as r:
        return json.loads(r.read())


DONE = ("SUCCEEDED", "FAILED", "STOPPED")


def job_status(c: Cluster, name: str) -> str:
    return jobs_api(c, c.jobs[name])["status"]


def wait_for_job(c: Cluster, name: str, timeout: float = 900) -> tuple[str, str]:
    """(final status, the job's output); the output is also kept in ROOT/<name>.log."""
    deadline = time.time() + timeout
    while (status := job_status(c, name)) not in DONE:
        assert time.time() < deadline, f"job {name} still {status} after {timeout:.0f} s"
        time.sleep(3)
    logs = jobs_api(c, f"{c.jobs[name]}/logs")["logs"]
    (c.root / f"{name}.log").write_text(logs)
    return status, logs


def mlflow_runs(c: Cluster) -> tuple[str, list[dict]]:
    def post(path: str, body: dict) -> dict:
        request = urllib.request.Request(f"{c.mlflow}/api/2.0/mlflow/{path}", json.dumps(body).encode(),
                                         {"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=30) as r:
            return json.loads(r.read())

    with urllib.request.urlopen(f"{c.mlflow}/api/2.0/mlflow/experiments/get-by-name?experiment_name=aniformer",
                                timeout=30) as r:
        experiment = json.loads(r.read())["experiment"]["experiment_id"]
    return experiment, post("runs/search", {"experiment_ids": [experiment], "max_results": 1000}).get("runs", [])


def tags(run: dict) -> dict:
    return {t["key"]: t["value"] for t in run["data"].get("tags", [])}


@dataclass
class Jobs:
    """The two jobs every later check looks at: the tiny training job and the tiny sweep, run at once."""

    train_out: Path
    train: tuple[str, str]  # (final status, output)
    sweep_out: Path
    sweep: tuple[str, str] | None  # None: not submitted (the training job made no mesh bank)


def run_jobs(cluster: Cluster) -> Jobs:
    """Submit the tiny training job through `ray job submit`, then the tiny sweep as soon as the training
    job's mesh bank exists (the two share the cluster, as they would on a real one); wait for both."""
    out = cluster.root / "runs" / "tiny"
    out.mkdir(parents=True)
    # A symlink planted in --out must be replaced, not written through (writes cannot escape --out).
    outside = cluster.root / "outside.txt"
    outside.write_text("untouched")
    (out / "last.pt").symlink_to(outside)
    submit(cluster, "train_job", "python", "jobs/train.py", "--config", "configs/tiny.yaml", "--out", str(out), *TRAIN)
    wait_for("the training job's mesh bank", lambda: (out / "bank" / "manifest.json").is_file()
             or job_status(cluster, "train_job") in DONE, cluster, timeout=600, every=3)
    sweep_out = cluster.root / "runs" / "sweep"
    if (out / "bank" / "manifest.json").is_file():
        submit(cluster, "sweep_job", "python", "jobs/sweep.py", "--config", "configs/sweep_tiny.yaml",
               "--out", str(sweep_out), "--bank", str(out / "bank"), *SWEEP)
    train = wait_for_job(cluster, "train_job")
    sweep = wait_for_job(cluster, "sweep_job") if "sweep_job" in cluster.jobs else None
    return Jobs(out, train, sweep_out, sweep)


def running(pid: int) -> bool:
    try:
        return (Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]) != "Z"
    except OSError:
        return False

"""System test: a real local Ray cluster started the way cluster.yaml starts one, jobs submitted with
`ray job submit`, tracked by our MLflow server and looked at in a real browser.

One module-scoped cluster (the CI machine has 2 cores, so it is started once):

- an MLflow tracking server (`python -m pipeline.mlflow_server`, what the cluster's head runs) on
  127.0.0.1 with its store and a backup directory;
- `ray start --head --block` bound to 127.0.0.1 with token authentication, and two worker nodes
  (`ray start --address=... --block`), each in its own process group and temp dir, every port
  chosen free (two Ray instances on one machine otherwise collide, e.g. on the dashboard agent's
  52365 or the autoscaler's and the dashboard's metrics ports 44217 and 44227);
- every node started with MLFLOW_TRACKING_URI in its environment, as cluster.yaml does, so jobs log
  to the server without being told (no runtime_env).

Each test sets up what it needs through fixtures, so any one runs alone or in any order: what
listens where, the token check, the tiny training job through `ray job submit` and a tiny sweep
submitted as soon as the training job's mesh bank exists (both run at once, the `jobs` fixture), the
MLflow UI in headless Chromium driven by Selenium WebDriver (the `browser` fixture, Debian's chromium-driver:
the runs list; then the compare view of the sweep's trials, clicked and typed through as a user would, with the
screenshot kept as docs/mlflow_ui.png when ANIFORMER_KEEP_SCREENSHOT names it), the server's backup on stop, and the local
Ray instance a job starts without a cluster. Everything is stopped through its own process group, never with `ray stop` (which
would kill every Ray on the machine).
"""

from __future__ import annotations

import csv
import json
import os
import secrets
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from selenium.common.exceptions import (
    ElementClickInterceptedException,
    ElementNotInteractableException,
    NoSuchElementException,
    StaleElementReferenceException,
    WebDriverException,
)
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys
from selenium.webdriver.support import expected_conditions as EC
from selenium.webdriver.support.ui import WebDriverWait

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
# the `browser` fixture (tests/conftest.py): Selenium WebDriver over Debian's chromium and chromium-driver
NEEDS_BROWSER = pytest.mark.skipif(
    not (shutil.which("chromium") or shutil.which("chromium-browser")) or not shutil.which("chromedriver"),
    reason="no chromium or chromedriver (.ci/run installs Debian's chromium and chromium-driver)")
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


def _start(cluster: Cluster, name: str, cmd: list[str], **env: str) -> None:
    log = cluster.root / f"{name}.log"
    if log.exists():  # a restart: keep the earlier log beside the new one
        log.rename(log.with_suffix(f".{time.time():.0f}.log"))
    cluster.logs[name] = log
    cluster.commands[name] = cmd
    with open(log, "w") as f:
        cluster.procs[name] = subprocess.Popen(cmd, env={**cluster.env, **env}, cwd=ROOT, stdout=f,
                                               stderr=subprocess.STDOUT, start_new_session=True)


def _stop(procs: list[subprocess.Popen], grace: float = 10) -> None:
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


def _wait(what: str, ok, cluster: Cluster, timeout: float = 240, every: float = 2, tolerate=()):
    deadline = time.time() + timeout
    while True:
        result = ok()
        if result:
            return result
        dead = [n for n, p in cluster.procs.items() if p.poll() is not None and n not in tolerate]
        assert not dead, f"{', '.join(dead)} exited while waiting for {what}:\n" + "\n".join(cluster.tail(n) for n in dead)
        assert time.time() < deadline, f"timed out waiting for {what}"
        time.sleep(every)


def _healthy(url: str) -> bool:
    try:
        with urllib.request.urlopen(f"{url}/health", timeout=5) as r:
            return r.status == 200
    except OSError:
        return False


@pytest.fixture(scope="module")
def cluster(tmp_path_factory, free_ports):
    root = tmp_path_factory.mktemp("system")
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
        _start(c, "mlflow", [sys.executable, "-m", "pipeline.mlflow_server", "--host", "127.0.0.1",
                             "--port", str(mlflow_port), "--store", str(root / "mlflow"),
                             "--backup", str(root / "mlflow-backup"), "--backup-every", "3600"])
        common = ["--block", "--node-ip-address=127.0.0.1", f"--object-store-memory={OBJECT_STORE}",
                  f"--min-worker-port={WORKER_PORTS.start}", f"--max-worker-port={WORKER_PORTS.stop - 1}"]
        _start(c, "head", [str(BIN / "ray"), "start", "--head", *common, "--num-cpus=2", f"--temp-dir={temp_dirs[0]}",
                           f"--port={gcs}",
                           "--include-dashboard=true", "--dashboard-host=127.0.0.1", f"--dashboard-port={dashboard}",
                           f"--ray-client-server-port={client}", f"--dashboard-agent-listen-port={head_agent}",
                           f"--dashboard-agent-grpc-port={head_agent_grpc}", f"--metrics-export-port={head_metrics}",
                           f"--runtime-env-agent-port={head_runtime_env}", f"--node-manager-port={head_nm}",
                           f"--object-manager-port={head_om}"],
               # fixed 44217 and 44227 otherwise: one per machine, taken by whichever Ray starts first
               AUTOSCALER_METRIC_PORT=str(autoscaler_metrics), DASHBOARD_METRIC_PORT=str(dashboard_metrics))
        _wait("the head", lambda: c.alive_nodes() == 1, c)  # workers join a head that is fully up
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
            _start(c, f"worker{i}", workers[f"worker{i}"])

        def joined() -> bool:
            # `ray start` gives a raylet 30 s to register (hard-coded in Ray 2.60): on a loaded 2-core
            # machine that can pass. Such a worker exits; clear its process group and start it again.
            for name, cmd in workers.items():
                proc = c.procs[name]
                if proc.poll() is not None:
                    assert "timed out during startup" in c.tail(name), f"{name} exited:\n{c.tail(name)}"
                    _stop([proc], grace=5)
                    _start(c, name, cmd)
            return c.alive_nodes() == 3

        _wait("three alive nodes", joined, c, timeout=400, tolerate=set(workers))
        _wait("the MLflow server", lambda: _healthy(c.mlflow), c)
        yield c
    finally:
        _stop([c.procs[n] for n in ("worker0", "worker1", "head", "mlflow") if n in c.procs])
        for i, temp_dir in enumerate(temp_dirs):  # keep the nodes' own logs beside the test's
            for log in Path(temp_dir).glob("session_*/logs/raylet*"):
                (root / f"node{i}-logs").mkdir(exist_ok=True)
                shutil.copyfile(log, root / f"node{i}-logs" / log.name)
            shutil.rmtree(temp_dir, ignore_errors=True)


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


def _jobs_api(c: Cluster, path: str) -> dict:
    request = urllib.request.Request(f"{c.dashboard}/api/jobs/{path}",
                                     headers={"Authorization": f"Bearer {c.env['RAY_AUTH_TOKEN']}"})
    with urllib.request.urlopen(request, timeout=30) as r:
        return json.loads(r.read())


DONE = ("SUCCEEDED", "FAILED", "STOPPED")


def job_status(c: Cluster, name: str) -> str:
    return _jobs_api(c, c.jobs[name])["status"]


def wait_for_job(c: Cluster, name: str, timeout: float = 900) -> tuple[str, str]:
    """(final status, the job's output); the output is also kept in ROOT/<name>.log."""
    deadline = time.time() + timeout
    while (status := job_status(c, name)) not in DONE:
        assert time.time() < deadline, f"job {name} still {status} after {timeout:.0f} s"
        time.sleep(3)
    logs = _jobs_api(c, f"{c.jobs[name]}/logs")["logs"]
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


# ------------------------------------------------------------------ the tests (any order)


def test_services_listen_only_where_intended(cluster):
    ours = cluster.pids()
    # The dashboard / job API and MLflow: 127.0.0.1 only, never all interfaces.
    assert addresses(cluster.dashboard_port, ours) == {"127.0.0.1"}
    assert addresses(cluster.mlflow_port, ours) == {"127.0.0.1"}
    # Ray itself listens on all interfaces for its node-to-node RPC (GCS, raylet, agents' gRPC; token-
    # checked, next test) and its Prometheus metrics, whatever the flags (Ray 2.60): only on the ports
    # we gave it. So do its worker processes (`ray::...`, once jobs have run: this test may come after
    # them), each on a port of the worker range every node was given. (On the cluster the security
    # group keeps all of them inside the cluster.)
    expected = cluster.ray_rpc_ports | cluster.metrics_ports
    unexpected = {f"{address}:{port} {command(pid)}" for (address, port), pid in listening_sockets(ours).items()
                  if address in WILDCARD and port not in expected
                  and not (port in cluster.worker_ports and command(pid).startswith("ray::"))}
    assert not unexpected, f"unexpected listeners on all interfaces: {unexpected}"


def test_a_wrong_token_is_refused(cluster):
    wrong = {**cluster.env, "RAY_AUTH_TOKEN": "0" * 64}
    intruder = cluster.ray("job", "list", "--address", cluster.dashboard, env=wrong)
    assert intruder.returncode != 0 and "token" in intruder.stderr.lower(), intruder.stderr[-2000:]
    # The GCS (listening on all interfaces) refuses a driver with the wrong token too.
    started = time.time()
    driver = subprocess.run([sys.executable, "-c", f"import ray; ray.init(address={cluster.gcs!r})"],
                            env={**wrong, "RAY_NUM_REDIS_GET_RETRIES": "3"}, capture_output=True, text=True, timeout=180)
    print(f"wrong-token driver refused after {time.time() - started:.1f} s")
    print((driver.stdout + driver.stderr)[-1500:])
    assert driver.returncode != 0 and "auth" in (driver.stdout + driver.stderr).lower(), driver.stderr[-2000:]
    assert cluster.alive_nodes() == 3  # the right token still works


@dataclass
class Jobs:
    """The two jobs every later check looks at: the tiny training job and the tiny sweep, run at once."""

    train_out: Path
    train: tuple[str, str]  # (final status, output)
    sweep_out: Path
    sweep: tuple[str, str] | None  # None: not submitted (the training job made no mesh bank)


@pytest.fixture(scope="module")
def jobs(cluster) -> Jobs:
    """Submit the tiny training job through `ray job submit`, then the tiny sweep as soon as the training
    job's mesh bank exists (the two share the cluster, as they would on a real one); wait for both. Any
    test that needs the runs asks for this, so each runs alone or in any order."""
    out = cluster.root / "runs" / "tiny"
    out.mkdir(parents=True)
    # A symlink planted in --out must be replaced, not written through (writes cannot escape --out).
    outside = cluster.root / "outside.txt"
    outside.write_text("untouched")
    (out / "last.pt").symlink_to(outside)
    submit(cluster, "train_job", "python", "jobs/train.py", "--config", "configs/tiny.yaml", "--out", str(out), *TRAIN)
    _wait("the training job's mesh bank", lambda: (out / "bank" / "manifest.json").is_file()
          or job_status(cluster, "train_job") in DONE, cluster, timeout=600, every=3)
    sweep_out = cluster.root / "runs" / "sweep"
    if (out / "bank" / "manifest.json").is_file():
        submit(cluster, "sweep_job", "python", "jobs/sweep.py", "--config", "configs/sweep_tiny.yaml",
               "--out", str(sweep_out), "--bank", str(out / "bank"), *SWEEP)
    train = wait_for_job(cluster, "train_job")
    sweep = wait_for_job(cluster, "sweep_job") if "sweep_job" in cluster.jobs else None
    return Jobs(out, train, sweep_out, sweep)


def test_training_job_submitted_to_the_cluster(cluster, jobs):
    status, logs = jobs.train
    assert status == "SUCCEEDED", logs[-5000:]
    out = jobs.train_out
    import torch

    from aniformer.checkpoint import load_checkpoint
    from aniformer.cli import load_config
    from pipeline.run_spec import RunSpec

    best, last = load_checkpoint(out / "best.pt"), load_checkpoint(out / "last.pt")
    assert best["config"] == RunSpec.from_config(load_config(ROOT / "configs/tiny.yaml", TRAIN)).to_dict()
    # one epoch: the best is the last, weight for weight
    assert best["epoch"] == last["epoch"] == 1 and best["model"].keys() == last["model"].keys()
    assert all(torch.equal(best["model"][k], last["model"][k]) for k in best["model"])
    # Logged to the server through the nodes' environment (no runtime_env), metrics by the trainer.
    _, runs = mlflow_runs(cluster)
    (run,) = [r for r in runs if r["info"]["run_name"] == "tiny"]
    assert run["info"]["status"] == "FINISHED"
    assert {m["key"] for m in run["data"].get("metrics", [])} >= {"pmd_unseen", "loss"}


def test_a_symlink_planted_in_out_is_replaced_not_written_through(cluster, jobs):
    last = jobs.train_out / "last.pt"
    assert last.exists(), "the training job did not run"
    assert (cluster.root / "outside.txt").read_bytes() == b"untouched" and not last.is_symlink()


def test_sweep_job_submitted_to_the_cluster(cluster, jobs):
    assert jobs.sweep is not None, "not submitted: the training job made no mesh bank"
    status, logs = jobs.sweep
    assert status == "SUCCEEDED", logs[-5000:]
    assert f"== sweep sweep: {TRIALS} trials (" in logs and "| trial " in logs, logs[-5000:]  # its table, in the job's log
    rows = list(csv.DictReader((jobs.sweep_out / "summary.csv").open()))
    assert len(rows) == TRIALS and all(r["status"] in ("ok", "early_stopped", "adjusted_memory") for r in rows), rows
    _, runs = mlflow_runs(cluster)
    (parent,) = [r for r in runs if r["info"]["run_name"] == "sweep"]
    children = [r for r in runs if tags(r).get("mlflow.parentRunId") == parent["info"]["run_id"]]
    assert parent["info"]["status"] == "FINISHED" and len(children) == TRIALS


@NEEDS_BROWSER
def test_mlflow_ui_in_a_real_browser_shows_the_runs(cluster, jobs, browser, tmp_path):
    experiment, runs = mlflow_runs(cluster)
    names = {r["info"]["run_name"] for r in runs}
    assert {"tiny", "sweep"} <= names
    shot = tmp_path / "mlflow_ui.png"
    driver = browser(1600, 900)
    driver.get(f"{cluster.mlflow}/#/experiments/{experiment}/runs")
    # the UI is a React app: it fetches the runs, then draws them (slowly on a loaded machine)
    for name in ("tiny", "sweep"):
        WebDriverWait(driver, 120).until(EC.visibility_of_element_located((By.XPATH, f"//*[text()={_literal(name)}]")),
                                         f"the run {name} in the runs list")
    dom = driver.page_source
    assert ">tiny<" in dom and ">sweep<" in dom, dom[-3000:]
    assert "matching runs" in dom or "Run Name" in dom
    driver.save_screenshot(shot)
    image = _png_stats(shot)
    assert image["width"] >= 1200 and image["height"] >= 800
    assert image["colours"] > 200 and 0.05 < image["ink"] < 0.95, image  # a rendered page, not a blank one


# ------------------------------------------------------------------ the compare view, clicked through with Selenium

SWEPT = ["loss.rec", "loss.motion", "loss.appearance", "data.window"]  # the sweep's searched params (tune.PARAMS)
# what a click or a wait may meet while the UI re-renders: the wait tries again
FLAKY = (StaleElementReferenceException, ElementClickInterceptedException, ElementNotInteractableException,
         NoSuchElementException)


def _literal(text: str) -> str:
    """`text` as an XPath string literal."""
    assert '"' not in text, text
    return f'"{text}"'


def _has_class(name: str) -> str:
    """An XPath predicate: the element has the class `name`."""
    return f"contains(concat(' ', normalize-space(@class), ' '), ' {name} ')"


def _shown(driver, xpath: str) -> list:
    """The displayed elements that `xpath` finds."""
    return [e for e in driver.find_elements(By.XPATH, xpath) if e.is_displayed()]


def _click(driver, xpath: str, what: str, timeout: float = 60) -> None:
    """Click, as a user does, the first displayed element `xpath` finds, once there is one: scroll it into
    view with the wheel, move the mouse to its middle and press there. (Not `WebElement.click()`: that
    refuses when the element at that point is another, as under a select's arrow, which lets clicks
    through to the select.)"""

    def clicked(d) -> bool:
        shown = _shown(d, xpath)
        if shown:
            ActionChains(d).scroll_to_element(shown[0]).move_to_element(shown[0]).click().perform()
        return bool(shown)

    WebDriverWait(driver, timeout, ignored_exceptions=FLAKY).until(clicked, f"{what} to click")


def _keys(driver, *keys: str, hold: str | None = None) -> None:
    """Type `keys` into whatever has the focus (the keyboard), holding `hold` (a modifier) down."""
    actions = ActionChains(driver)
    if hold:
        actions.key_down(hold)
    actions.send_keys(*keys)
    if hold:
        actions.key_up(hold)
    actions.perform()


def _text(driver) -> str:
    return driver.execute_script("return document.body ? document.body.innerText : ''")


def _choose(driver, field: str, keys: list[str]) -> list[str]:
    """Pick `keys` in the multiple-choice select after the label `field` ("Parameters:", "Metrics:") of the
    parallel-coordinates controls: open it (its arrow, away from the chosen tags and their remove buttons),
    type the key, click the option that matches it exactly."""
    select = f"//div[.={_literal(field)}]/following-sibling::*[1]"
    options = f"//*[{_has_class('du-bois-light-select-item-option')}]"

    def box(d):
        return d.find_element(By.XPATH, f"{select}//input")

    def chosen(d) -> list[str]:
        return [e.get_property("textContent") for e in
                d.find_elements(By.XPATH, f"{select}//*[{_has_class('du-bois-light-select-selection-item-content')}]")]

    def wait(condition, what: str):
        return WebDriverWait(driver, 10, ignored_exceptions=FLAKY).until(condition, what)

    for key in keys:
        for attempt in range(3):  # a click or keys landing while the UI re-renders: try again
            try:
                wait(lambda d: not _shown(d, options), "no dropdown open")
                _click(driver, f"{select}//*[{_has_class('du-bois-light-select-arrow')}]", f"the {field} arrow", timeout=10)
                wait(lambda d: d.switch_to.active_element == box(d), f"focus on the {field} box")
                if box(driver).get_property("value"):  # what was typed for the last one may still be there
                    _keys(driver, "a", hold=Keys.CONTROL)
                    _keys(driver, Keys.BACKSPACE)
                    wait(lambda d: box(d).get_property("value") == "", f"an empty {field} box")
                _keys(driver, key)
                _click(driver, f"{options}[.={_literal(key)}]", f"option {key}", timeout=10)
                wait(lambda d, key=key: key in chosen(d), f"{key} chosen")
                break
            except WebDriverException as e:
                if attempt == 2:
                    state = [box(driver).get_property("value"), chosen(driver),
                             [o.get_property("textContent") for o in _shown(driver, options)][:10]]
                    raise AssertionError(f"{field} {key}: {e.msg} (typed, chosen, options shown: {state})") from None
            finally:
                _keys(driver, Keys.ESCAPE)
    return chosen(driver)


def _pick(driver, select_id: str, key: str) -> None:
    """Choose `key` in the single-choice select (a button that opens a list of options) `select_id`."""
    button = f"//*[@id={_literal(select_id)}]"
    listed = "//*[@role='option']"
    for attempt in range(3):
        try:
            WebDriverWait(driver, 10, ignored_exceptions=FLAKY).until(lambda d: not _shown(d, listed), "no list open")
            _click(driver, button, select_id, timeout=10)
            _click(driver, f"{listed}[.={_literal(key)}]", f"option {key}", timeout=10)
            WebDriverWait(driver, 10, ignored_exceptions=FLAKY).until(
                lambda d: d.find_element(By.XPATH, button).get_property("textContent") == key, f"{key} in {select_id}")
            return
        except WebDriverException as e:
            if attempt == 2:
                shown = [driver.find_element(By.XPATH, button).get_property("textContent"),
                         [o.get_property("textContent") for o in _shown(driver, listed)][:10]]
                raise AssertionError(f"{select_id} {key}: {e.msg} (shown, options: {shown})") from None
            if _shown(driver, listed):
                _keys(driver, Keys.ESCAPE)


def _compare_view(driver, url: str, names: list[str], shot: Path) -> dict:
    """Open the compare view of a sweep's trials; plot the swept params and pmd_unseen in parallel
    coordinates (screenshot with the params that differ), then each swept param against pmd_unseen
    in the scatter plot. What the page showed."""
    import io

    from PIL import Image  # matplotlib's dependency

    seen = {}
    driver.get(url)
    WebDriverWait(driver, 60).until(lambda d: all(s in _text(d) for s in ["Parallel Coordinates Plot", *names]),
                                    "the compare view of the trials")
    close = "//*[@data-component-id='mlflow.assistant.chat_panel.close']"
    if _shown(driver, close):  # MLflow 3's assistant panel takes a third of the width
        _click(driver, close, "the assistant's close button")
    _click(driver, "//button[.='Clear All']", "Clear All")
    seen["params"] = _choose(driver, "Parameters:", SWEPT)
    seen["metrics"] = _choose(driver, "Metrics:", ["pmd_unseen"])
    plot = "document.querySelector('[id$=content-parallel-coordinates-plot] .js-plotly-plot')"
    WebDriverWait(driver, 60).until(
        lambda d: d.execute_script(f"const p = {plot}; return !!(p && p.data && p.data[0].dimensions.length === 5)"),
        f"the 5 axes (chosen: {seen['params']}, {seen['metrics']})")
    seen["axes"] = driver.execute_script(f"return {plot}.data[0].dimensions.map(d => [d.label, d.values])")
    seen["axis_titles"] = [e.get_property("textContent")
                           for e in driver.find_elements(By.CSS_SELECTOR, ".parcoords .axis-title")]
    diff = "//button[@aria-label='Parameters - Show diff only']"
    _click(driver, diff, "Parameters: show diff only")
    WebDriverWait(driver, 60, ignored_exceptions=FLAKY).until(
        lambda d: d.find_element(By.XPATH, diff).get_attribute("aria-checked") == "true", "only the params that differ")
    driver.execute_script("[...document.querySelectorAll('*')].forEach(e => { if (e.scrollTop) e.scrollTop = 0; })")
    table = driver.find_element(By.XPATH, f"{diff}/ancestor::*[{_has_class('du-bois-light-collapse-content-box')}][1]//table")
    bottom = table.rect["y"] + table.rect["height"]
    seen["text"] = _text(driver)
    with Image.open(io.BytesIO(driver.get_screenshot_as_png())) as page:  # from the top to the end of those params
        page.crop((0, 0, page.width, min(page.height, int(bottom) + 24))).save(shot)
    _click(driver, "//*[@role='tab'][.='Scatter Plot']", "the Scatter Plot tab")
    scatter = "document.querySelector('[id$=content-scatter-plot] .js-plotly-plot')"
    seen["scatter"] = {}
    for param in SWEPT:
        for axis, key in (("x", param), ("y", "pmd_unseen")):
            _pick(driver, f"{axis}-axis-selector", key)
        seen["scatter"][param] = driver.execute_script(
            f"const t = {scatter}.data[0]; "
            "return {x: t.x, y: t.y, names: t.text.map(s => s.split('</b>')[0].replace('<b>', ''))};")
    return seen


@NEEDS_BROWSER
def test_mlflow_compare_view_shows_the_sweeps_trials_in_a_real_browser(cluster, jobs, browser, tmp_path):
    """The compare view of the sweep's children (the link `pipeline.sweep_table.compare_link` prints), as a user
    reaches it: parallel coordinates over lambda_rec, lambda_m, lambda_a, T and pmd_unseen, the scatter of
    each against pmd_unseen; the values drawn are the runs' own. Screenshot: ANIFORMER_KEEP_SCREENSHOT
    (docs/mlflow_ui.png)."""
    from pipeline.sweep_table import compare_url

    experiment, runs = mlflow_runs(cluster)
    (parent,) = [r for r in runs if r["info"]["run_name"] == "sweep"]
    children = sorted((r for r in runs if tags(r).get("mlflow.parentRunId") == parent["info"]["run_id"]),
                      key=lambda r: r["info"]["run_name"])
    assert len(children) == TRIALS, "the sweep job did not run"
    params = [{p["key"]: p["value"] for p in r["data"]["params"]} for r in children]
    pmd = [{m["key"]: m["value"] for m in r["data"]["metrics"]}["pmd_unseen"] for r in children]
    names = [r["info"]["run_name"] for r in children]
    url = compare_url(cluster.mlflow, experiment, [r["info"]["run_id"] for r in children])
    shot = tmp_path / "mlflow_compare.png"
    started = time.time()
    # Tall enough that nothing scrolls (the page scrolls inside its own panel; resizing later can
    # re-mount the plot's controls, losing what was chosen): the screenshot is the top of it.
    seen = _compare_view(browser(1600, 3000), url, names, shot)
    print(f"compare view driven in {time.time() - started:.1f} s")

    assert seen["params"] == SWEPT and seen["metrics"] == ["pmd_unseen"], seen
    assert seen["axis_titles"] == [*SWEPT, "pmd_unseen"], seen["axis_titles"]
    # the lines are the trials: each axis holds the runs' values (the UI's run order is the URL's)
    axes = dict((label, values) for label, values in seen["axes"])
    for key in SWEPT:
        assert sorted(axes[key]) == pytest.approx(sorted(float(p[key]) for p in params)), key
    assert sorted(axes["pmd_unseen"]) == pytest.approx(sorted(pmd))
    text = seen["text"]
    assert all(name in text for name in names) and "Show diff only" in text
    for p in params:  # the diff-only table: the swept values of every trial
        assert p["loss.rec"] in text and p["loss.appearance"] in text, p
    for key in SWEPT:  # each swept value against pmd_unseen, one point per trial, named
        points = seen["scatter"][key]
        by_name = {n: (float(x), y) for n, x, y in zip(points["names"], points["x"], points["y"])}
        assert by_name == {n: (pytest.approx(float(p[key])), pytest.approx(v)) for n, p, v in zip(names, params, pmd)}
    image = _png_stats(shot)
    assert image["width"] == 1600 and image["height"] >= 900, image
    assert image["colours"] > 200 and 0.05 < image["ink"] < 0.95, image
    keep = os.environ.get("ANIFORMER_KEEP_SCREENSHOT")
    if keep:
        shutil.copyfile(shot, keep)


def _png_stats(path: Path) -> dict:
    import numpy as np
    from PIL import Image  # matplotlib's dependency

    with Image.open(path) as im:
        rgb = np.asarray(im.convert("RGB"))
    packed = (rgb[..., 0].astype(np.int64) << 16) | (rgb[..., 1].astype(np.int64) << 8) | rgb[..., 2]
    return {"width": rgb.shape[1], "height": rgb.shape[0], "colours": len(np.unique(packed)),
            "ink": float((rgb.min(axis=-1) < 240).mean())}  # share of pixels that are not (near) white


def test_stopping_the_mlflow_server_leaves_a_backup_with_the_runs(cluster, jobs):
    """Stopped, the server backs its store up; it is then started again on the same store, as the
    cluster's head would restart it, so that the tests after this one find it (any order)."""
    server = cluster.procs["mlflow"]
    started = tree_pids(server.pid)
    os.kill(server.pid, signal.SIGTERM)  # the wrapper: stops its server, then backs the store up
    try:
        server.wait(timeout=120)
        assert server.returncode == 0, cluster.tail("mlflow")
        assert not [pid for pid in started if _running(pid)], "the MLflow server left processes behind"
        with sqlite3.connect(cluster.root / "mlflow-backup" / "mlflow.db") as db:
            names = {name for (name,) in db.execute("select name from runs")}
        assert {"tiny", "sweep"} <= names
    finally:
        _stop([server], grace=30)
        _start(cluster, "mlflow", cluster.commands["mlflow"])
        _wait("the MLflow server, started again", lambda: _healthy(cluster.mlflow), cluster)
    _, runs = mlflow_runs(cluster)  # the same store, served again
    assert {"tiny", "sweep"} <= {r["info"]["run_name"] for r in runs}


def _running(pid: int) -> bool:
    try:
        return (Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]) != "Z"
    except OSError:
        return False


def test_jobs_without_a_cluster_start_a_local_ray_on_localhost_with_token_auth(tmp_path, read_line):
    """jobs/*.py without RAY_ADDRESS call pipeline.cluster.connect(): a private local Ray instance."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["RAY_TMPDIR"] = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    script = ("import json, sys, ray\n"
              "from pipeline.cluster import connect\n"
              "from ray._raylet import AuthenticationMode, get_authentication_mode\n"
              "connect()\n"
              "info = ray._private.worker.global_worker.node.address_info\n"
              "token = get_authentication_mode() == AuthenticationMode.TOKEN\n"
              "print(json.dumps({'dashboard': info['webui_url'], 'token': token}), flush=True)\n"
              "sys.stdin.read()\n")
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, env=env, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, start_new_session=True)
    try:
        info = json.loads(read_line(proc.stdout, 180, "the local Ray driver (its dashboard address)") or "null")
        assert info, "the local Ray driver exited before it printed its dashboard address"
        port = int(info["dashboard"].rsplit(":", 1)[1])
        assert addresses(port, tree_pids(proc.pid)) == {"127.0.0.1"}
        assert info["token"], "the local Ray instance runs without token authentication"
    finally:
        proc.stdin.close()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            pass
        kill_group(proc.pid)
        shutil.rmtree(env["RAY_TMPDIR"], ignore_errors=True)


def test_a_local_ray_answers_rays_own_cluster_lookups_not_the_cluster_recorded_last(tmp_path, ray_address):
    """Ray Train's placement-group cleaner asks, with no address, whether the train controller lives. With
    another cluster recorded as this machine's last (here: the test session's), Ray looked there, found no
    such actor, and the cleaner removed the training's placement group, killing its workers. A job's local
    Ray must find its own actors."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["RAY_TMPDIR"] = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    (Path(env["RAY_TMPDIR"]) / "ray").mkdir()
    (Path(env["RAY_TMPDIR"]) / "ray" / "ray_current_cluster").write_text(ray_address)  # as `ray start` leaves it
    script = ("import ray\n"
              "from ray.train.v2._internal.state.util import is_actor_alive\n"
              "from pipeline.cluster import connect\n"
              "connect()\n"
              "Probe = ray.remote(num_cpus=0)(type('Probe', (), {'ping': lambda self: True}))\n"
              "probe = Probe.options(lifetime='detached').remote()\n"
              "ray.get(probe.ping.remote())\n"
              "alive = ray.remote(num_cpus=0)(lambda actor_id: bool(is_actor_alive(actor_id, timeout=30)))\n"
              "print('alive' if ray.get(alive.remote(probe._actor_id.hex())) else 'not found', flush=True)\n")
    try:
        proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=300)
        assert proc.stdout.strip().splitlines()[-1:] == ["alive"], proc.stdout[-2000:] + proc.stderr[-2000:]
    finally:
        shutil.rmtree(env["RAY_TMPDIR"], ignore_errors=True)

"""Shared fixtures: one real local multi-node Ray cluster of CPU workers per pytest session.

``ray_cluster`` starts a head node and one worker node (1 CPU each: 2 in all, what a 2-core
machine can run) with ``ray.cluster_utils.Cluster``, connects this process with
``ray.init(address=cluster.address)`` once and shuts everything down at the end of the session.
Tests may add or remove nodes on the yielded ``Cluster`` (``add_node``/``remove_node``); they
must leave it as they found it. ``ray_address`` gives the address for subprocesses
(``RAY_ADDRESS=...``), so jobs run as scripts join the same cluster instead of starting their own.
"""

from __future__ import annotations

import os
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NODE = {"num_cpus": 1, "object_store_memory": 512 * 1024**2}  # each node of `ray_cluster`


@pytest.fixture(scope="session", autouse=True)
def fit_cache(tmp_path_factory) -> Path:
    """The session's registrations are kept in a directory of its own (inherited by the Ray cluster and the
    jobs it starts), not in the user's ``~/.cache/aniformer``; every session registers afresh."""
    from aniformer.registration import CACHE_ENV

    path = tmp_path_factory.mktemp("fits")
    os.environ[CACHE_ENV] = str(path)
    return path


def pick_free_ports(n: int) -> list[int]:
    """n distinct free TCP ports between Ray's worker ports (10002-19999) and the kernel's ephemeral range:
    a port handed out by `bind(0)` could be taken by any process binding port 0 (Ray's gRPC servers and
    workers do) before the test's server binds it."""
    import random
    import socket

    low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    chosen = []
    for port in random.sample(range(20000, low), min(4 * n + 50, low - 20000)):  # distinct candidates
        with socket.socket() as s:
            try:
                s.bind(("", port))  # every address: free on 127.0.0.1 and for a server binding 0.0.0.0
            except OSError:
                continue
        chosen.append(port)
        if len(chosen) == n:
            return chosen
    raise RuntimeError(f"could not find {n} free ports")


@pytest.fixture(scope="session")
def free_ports():
    """``free_ports(n)``: n distinct TCP ports that nothing listens on, outside Ray's worker ports and the
    ephemeral range, for servers a test starts (or a port that must refuse connections)."""
    return pick_free_ports


@pytest.fixture(scope="session")
def node_args() -> dict:
    """What each node of ``ray_cluster`` is started with: ``ray_cluster.add_node(**node_args)`` adds one back."""
    return dict(NODE)


@pytest.fixture(scope="session")
def ray_cluster():
    """The session's local Ray cluster (head + 1 worker node, 1 CPU each), already connected."""
    import ray
    from ray.cluster_utils import Cluster

    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    dashboard_port, agent_port = pick_free_ports(2)  # 8265 may belong to another Ray on this machine
    # Ray Train's placement-group cleaner looks its cluster up with no address: without this it may ask
    # another Ray on the machine and remove a live training's placement group (pipeline/cluster.py).
    os.environ["RAY_API_SERVER_ADDRESS"] = f"http://127.0.0.1:{dashboard_port}"
    cluster = Cluster(
        initialize_head=True,
        head_node_args={
            **NODE,
            # Ray Train's controller wants the dashboard; bind it to localhost only.
            "include_dashboard": True,
            "dashboard_host": "127.0.0.1",
            "dashboard_port": dashboard_port,
            # The head's dashboard agent defaults to 52365; a second head on this machine (the job
            # submission tests' `ray start --head`) would lose its agent and refuse every job.
            "dashboard_agent_listen_port": agent_port,
        },
    )
    cluster.add_node(**NODE)
    cluster.wait_for_nodes()
    ray.init(address=cluster.address)
    try:
        yield cluster
    finally:
        ray.shutdown()
        cluster.shutdown()


@pytest.fixture(scope="session")
def ray_address(ray_cluster) -> str:
    """Address of the session cluster, for ``RAY_ADDRESS`` in subprocesses."""
    return ray_cluster.address


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


@pytest.fixture(scope="session")
def job_main():
    """`job_main("train")`: jobs/train.py's `main`, loaded once per session, to run in this process
    under `aniformer.cli.exits.run` (a subprocess per case costs seconds of imports)."""
    import importlib

    return lambda name: importlib.import_module(f"jobs.{name}").main


@pytest.fixture(scope="session")
def bench_module():
    """`bench_module("model_bench")`: bench/model_bench.py as a module, loaded once per session by its path
    (bench/ is scripts, not a package: nothing is added to sys.path for the tests after it)."""
    import functools
    import importlib.util

    @functools.cache
    def load(name: str):
        spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "bench" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture(scope="session")
def scoring():
    """What a job's PMD table must say, recomputed independently of ``aniformer.evaluate``:
    ``scoring.pmd(sampler, split, pairs, predict, frames)``, with ``scoring.static_target`` and
    ``scoring.model_predict(model)`` as predictors (None: copy-driver)."""
    return types.SimpleNamespace(pmd=recomputed_pmd, static_target=static_target, model_predict=model_predict)


@pytest.fixture(scope="session")
def read_line():
    """``read_line(stream, timeout, what)``: one line of a pipe within ``timeout`` seconds (``readline``)."""
    return readline


def readline(stream, timeout: float, what: str) -> str:
    """One line of `stream` (a pipe: it has no read timeout), read by a thread; fails after `timeout`
    seconds naming `what`. At EOF it is "" as readline gives it."""
    import queue
    import threading

    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: lines.put(stream.readline()), daemon=True).start()
    try:
        return lines.get(timeout=max(timeout, 0.1))
    except queue.Empty:
        raise AssertionError(f"no line from {what} within {timeout:.0f} s") from None


def recomputed_pmd(sampler, split: str, pairs: int, predict=None, frames: slice = slice(None)) -> float:
    """Mean PMD x1e4 over pairs 0..pairs-1 of `split`, recomputed here in float64 numpy from the sampler's
    batch, not through `aniformer.evaluate`: what a job's table must say. `predict(batch)` gives the
    `(B, T', V, 3)` prediction of `frames` of each window; None is the copy-driver."""
    import numpy as np

    from aniformer.metrics import PMD_SCALE

    batch = sampler.batch(split, 0, np.arange(pairs), n=pairs)
    pred = batch["driving"] if predict is None else predict(batch)
    error = np.asarray(pred, np.float64) - np.asarray(batch["ground_truth"][:, frames], np.float64)
    return float((error ** 2).sum(-1).mean() * PMD_SCALE)


def static_target(batch):
    """`predict` for `recomputed_pmd`: the target, unmoved, in every frame of the window."""
    import numpy as np

    return np.repeat(batch["target"][:, None], batch["driving"].shape[1], axis=1)


def model_predict(model):
    """`predict` for `recomputed_pmd`: the model in eval mode on a batch's driving, target and faces."""
    import numpy as np
    import torch

    model.eval()

    def predict(batch):
        with torch.no_grad():
            inputs = [None if batch.get(k) is None else torch.from_numpy(np.ascontiguousarray(batch[k]))
                      for k in ("driving", "target", "target_faces")]
            return model(*inputs).float().numpy()

    return predict


CHROMEDRIVER = "/usr/bin/chromedriver"  # Debian's chromium-driver: the same build as its chromium


@pytest.fixture
def browser(tmp_path_factory):
    """``browser(width, height)``: a fresh headless Chromium driven by Selenium WebDriver (Debian's chromium
    and chromium-driver, which .ci/run installs), its viewport that size, its own profile; quit when the
    test ends. Skips the test where either is missing."""
    import shutil

    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None or not os.access(CHROMEDRIVER, os.X_OK):
        pytest.skip("no chromium or chromedriver (.ci/run installs Debian's chromium and chromium-driver)")
    drivers = []

    def start(width: int = 1600, height: int = 900):
        options = webdriver.ChromeOptions()
        options.binary_location = chromium
        for arg in ("--headless=new", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-sync",
                    "--disable-background-networking", "--disable-component-update", "--disable-breakpad",
                    "--hide-scrollbars", f"--window-size={width},{height}",
                    f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}"):
            options.add_argument(arg)
        if os.geteuid() == 0:
            options.add_argument("--no-sandbox")  # Chromium's sandbox refuses to run as root
        driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
        drivers.append(driver)
        driver.set_page_load_timeout(120)
        # the window is the viewport plus what the browser draws around it (143 px of height, headless)
        extra_width, extra_height = driver.execute_script("return [outerWidth - innerWidth, outerHeight - innerHeight]")
        if extra_width or extra_height:
            driver.set_window_size(width + extra_width, height + extra_height)
        assert driver.execute_script("return [innerWidth, innerHeight]") == [width, height]
        return driver

    yield start
    for driver in drivers:
        driver.quit()


# ------------------------------------------------------------------ the system tests' cluster and jobs
# tests/test_cluster_jobs.py, test_cluster_mlflow_ui.py and test_cluster_security.py share one cluster and
# one pair of jobs, started once per session (the machinery: tests/cluster_helpers.py).

_UNTIL_LAST_USE: dict = {}  # fixture name -> ExitStack that stops what it started: see pytest_runtest_teardown


@pytest.fixture(scope="session")
def cluster(tmp_path_factory, free_ports):
    """A real local Ray cluster started as cluster.yaml starts one (head + 2 worker nodes, `ray start`, token
    authentication) with our MLflow server, every process in a group of its own
    (``cluster_helpers.started_cluster``). Started once per session; stopped after the last test that asks
    for it."""
    import contextlib

    from cluster_helpers import started_cluster

    with contextlib.ExitStack() as stack:
        started = stack.enter_context(started_cluster(tmp_path_factory.mktemp("system"), free_ports))
        _UNTIL_LAST_USE["cluster"] = stack
        try:
            yield started
        finally:
            _UNTIL_LAST_USE.pop("cluster", None)


@pytest.fixture(scope="session")
def jobs(cluster):
    """The tiny training job submitted through `ray job submit`, then the tiny sweep as soon as the training
    job's mesh bank exists (the two share the cluster, as they would on a real one), both waited for
    (``cluster_helpers.run_jobs``): a ``cluster_helpers.Jobs``. Run once per session; any test that needs
    the runs asks for this, so each runs alone or in any order."""
    from cluster_helpers import run_jobs

    return run_jobs(cluster)


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem):
    """Stop the `cluster` (3 Ray nodes and an MLflow server) once no test left to run asks for it, rather than
    at the end of the session: the tests after it get the machine's 2 cores to themselves."""
    stack = _UNTIL_LAST_USE.get("cluster")
    if stack is None:
        return
    items = item.session.items
    later = items[items.index(item) + 1:] if item in items else ()
    if not any("cluster" in getattr(other, "fixturenames", ()) for other in later):
        _UNTIL_LAST_USE.pop("cluster", None)
        stack.close()

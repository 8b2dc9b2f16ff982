"""System test, a job's local Ray: jobs without a cluster (no RAY_ADDRESS) start a private local Ray
instance on localhost with token authentication, and that instance answers Ray's own cluster lookups
rather than the cluster this machine recorded last. No system cluster needed: each test starts its own.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from cluster_helpers import ROOT, addresses, kill_group, tree_pids

pytestmark = pytest.mark.slow


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

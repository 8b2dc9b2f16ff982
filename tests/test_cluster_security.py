"""System test, security: on the real local Ray cluster (the session's `cluster` fixture, tests/conftest.py;
tests/cluster_helpers.py starts it the way cluster.yaml starts one), what listens where, and the token
check of Ray's job API and of its GCS. Each test sets up what it needs through fixtures, so any one runs
alone or in any order.
"""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from cluster_helpers import WILDCARD, addresses, command, listening_sockets

pytestmark = pytest.mark.slow


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

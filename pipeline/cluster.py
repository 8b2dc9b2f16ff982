"""Connect to Ray: the cluster named by RAY_ADDRESS (set by `ray job submit`), else a new local one.

"A new local one" on purpose: plain `ray.init()` would join whichever cluster was started last on
this machine, which makes a job's behaviour depend on unrelated processes.

The local instance listens on 127.0.0.1 only: its node IP is 127.0.0.1, so the GCS, the raylet, the
workers, the dashboard and its agents, the runtime-env agent and the three Prometheus exporters
(the node's metrics agent, the autoscaler's, the dashboard's) all bind the loopback address. Ray
(2.60) turns a node IP of 127.0.0.1 into the machine's external address unless its Windows/macOS
"no cluster" switch is off; `_local_node_only` sets that switch for this process and its children.
The dashboard and job API run arbitrary code for whoever reaches them, and the exporters answer
without authentication. tests/test_limits.py lists a local job's listening sockets.
"""

from __future__ import annotations

import os

import ray

LOCALHOST = "127.0.0.1"
# Ray's switch for Windows and macOS, where it runs single-node on the loopback address by default.
SINGLE_NODE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def _local_node_only() -> None:
    """Make Ray keep a node IP of 127.0.0.1 instead of replacing it by the external address."""
    from ray._private import ray_constants

    os.environ[SINGLE_NODE_ENV] = "0"  # the agents and workers Ray starts read it at their import
    ray_constants.ENABLE_RAY_CLUSTER = False  # this process imported ray before the variable was set


def connect() -> str | None:
    """Connect (once per process); returns the Ray dashboard's address, None if already connected or none."""
    if ray.is_initialized():
        return None
    address = os.environ.get("RAY_ADDRESS")
    if address:
        return ray.init(address=address, log_to_driver=True).dashboard_url or None
    _local_node_only()
    context = ray.init(address="local", _node_ip_address=LOCALHOST, include_dashboard=True, dashboard_host=LOCALHOST,
                       log_to_driver=True)
    node_ip = ray.util.get_node_ip_address()
    if node_ip != LOCALHOST:  # a Ray release that resolves the address another way: never listen outside
        ray.shutdown()
        raise RuntimeError(f"the local Ray instance took node IP {node_ip}, not {LOCALHOST}: it would listen "
                           "beyond this machine")
    return context.dashboard_url or None

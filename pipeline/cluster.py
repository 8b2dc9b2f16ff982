"""Connect to Ray: the cluster named by RAY_ADDRESS (set by `ray job submit`), else a new local one.

"A new local one" on purpose: plain `ray.init()` would join whichever cluster was started last on
this machine, which makes a job's behaviour depend on unrelated processes.

The local instance keeps its dashboard (Ray Train's controller needs it) on 127.0.0.1 only: the
dashboard and job API run arbitrary code for whoever reaches them.
"""

from __future__ import annotations

import os

import ray


def connect() -> None:
    if ray.is_initialized():
        return
    address = os.environ.get("RAY_ADDRESS")
    if address:
        ray.init(address=address, log_to_driver=True)
    else:
        ray.init(address="local", include_dashboard=True, dashboard_host="127.0.0.1", log_to_driver=True)

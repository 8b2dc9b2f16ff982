"""Connect to Ray: the cluster named by RAY_ADDRESS (set by `ray job submit`), else a new local one.

"A new local one" on purpose: plain `ray.init()` would join whichever cluster was started last on
this machine, which makes a job's behaviour depend on unrelated processes.

The local instance listens on 127.0.0.1 only: its node IP is 127.0.0.1, so the GCS, the raylet, the
workers, the dashboard and its agents, the runtime-env agent and the three Prometheus exporters
(the node's metrics agent, the autoscaler's, the dashboard's) all bind the loopback address. Ray
(2.60) turns a node IP of 127.0.0.1 into the machine's external address unless its Windows/macOS
"no cluster" switch is off; `_local_node_only` sets that switch for this process and its children.
The dashboard and job API run arbitrary code for whoever reaches them, and the exporters answer
without authentication. tests/test_limits.py lists a local job's listening sockets. It runs with
Ray's token authentication (Ray's default for a new local cluster; tests/test_system.py checks it).

The local instance also answers Ray's own "which cluster?" lookups. Ray Train's placement-group
cleaner (a detached actor) asks the state API whether the train controller still lives, with no
address: Ray then takes the cluster recorded last on this machine (`ray start`, a test suite's
`ray.cluster_utils.Cluster`), not its own, finds no such controller there, and removes the
training's placement group, killing its workers. `connect` chooses the local dashboard's port
itself and names it in RAY_API_SERVER_ADDRESS, which Ray's lookup reads first, for this process
and every worker Ray starts.

A cluster that cannot be reached is one line (`UserError`), not Ray's traceback. `ray.init` has no
timeout of its own (ray-project/ray#46863): for an address where nothing answers it retries the GCS
connection 20 times, about 41 s each (14 min in all), and as long for an address where something
other than Ray listens. So `connect` first opens a TCP connection to the address Ray will dial, then
a gRPC channel (the GCS speaks gRPC; a web server or a silent listener never completes its HTTP/2
handshake), each within `PROBE_SECONDS`; what `ray.init` still raises is caught and shortened.
"""

from __future__ import annotations

import logging
import os
import socket

import ray

from aniformer.errors import UserError, root_cause

LOCALHOST = "127.0.0.1"
# Ray's switch for Windows and macOS, where it runs single-node on the loopback address by default.
SINGLE_NODE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
# Where Ray's state API and job clients look before RAY_ADDRESS and the last recorded cluster.
API_SERVER_ENV = "RAY_API_SERVER_ADDRESS"
PROBE_SECONDS = 5.0


def _local_node_only() -> None:
    """Make Ray keep a node IP of 127.0.0.1 instead of replacing it by the external address."""
    from ray._private import ray_constants

    os.environ[SINGLE_NODE_ENV] = "0"  # the agents and workers Ray starts read it at their import
    ray_constants.ENABLE_RAY_CLUSTER = False  # this process imported ray before the variable was set


def _free_local_port() -> int:
    """A TCP port free on 127.0.0.1 now, from the kernel's ephemeral range."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((LOCALHOST, 0))
        return probe.getsockname()[1]


def root_line(error: BaseException) -> str:
    """A Ray error and its root cause (`aniformer.errors.root_cause`) in one line. Ray puts a whole
    traceback into its "Failed to connect to GCS" message: the traceback's last line is the exception."""
    outer = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    error = root_cause(error)
    lines = [line.strip() for line in str(error).splitlines() if line.strip()] or [type(error).__name__]
    root = lines[-1] if "Traceback (most recent call last)" in str(error) else lines[0]
    return outer if root == outer else f"{outer} ({root})"


def probe_cluster(address: str) -> None:
    """Refuse, in one line and within `PROBE_SECONDS` per probe, a RAY_ADDRESS where nothing listens or
    something other than a Ray head does."""
    if "://" in address:  # a Ray Client or job server URL: ray.init's own errors are shortened below
        return
    from ray._private import services

    try:  # what Ray will dial: "auto" looked up, 127.0.0.1 replaced by the node's address
        target = services.canonicalize_bootstrap_address(address)
    except ValueError as error:
        raise UserError(f"RAY_ADDRESS {address!r}: {error}; expected HOST:PORT of a Ray cluster's head") from None
    if target is None:  # "local", or "auto" with no cluster recorded: ray.init decides
        return
    host, _, port = target.rpartition(":")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise UserError(f"RAY_ADDRESS {address!r}: the port {port!r} is not a number in 1-65535")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=PROBE_SECONDS).close()
    except OSError as error:
        reason = f"no answer in {PROBE_SECONDS:g} s" if isinstance(error, TimeoutError) else error.strerror or error
        raise UserError(f"RAY_ADDRESS {address}: no Ray cluster answers at {target} ({reason}); start one "
                        "(ray start --head) or unset RAY_ADDRESS to run on a local Ray") from None
    _probe_grpc(address, target)


def _probe_grpc(address: str, target: str) -> None:
    """Refuse an address that accepts TCP but is not a gRPC server, such as Ray's GCS, within `PROBE_SECONDS`."""
    import grpc
    from ray._private.gcs_utils import create_gcs_channel

    channel = create_gcs_channel(target)  # Ray's own channel: its TLS and token settings
    try:
        grpc.channel_ready_future(channel).result(timeout=PROBE_SECONDS)
    except grpc.FutureTimeoutError:
        raise UserError(f"RAY_ADDRESS {address}: something listens at {target} but it is not a Ray cluster's head "
                        f"(no gRPC handshake in {PROBE_SECONDS:g} s); check the address and port (GCS: 6379)") from None
    finally:
        channel.close()


def connect() -> str | None:
    """Connect (once per process); returns the Ray dashboard's address, None if already connected or none.
    `UserError` (one line) when the cluster of RAY_ADDRESS cannot be reached or a local one cannot start."""
    if ray.is_initialized():
        return None
    address = os.environ.get("RAY_ADDRESS")
    if address:
        probe_cluster(address)
        try:
            return ray.init(address=address, log_to_driver=True).dashboard_url or None
        except (ConnectionError, RuntimeError) as error:
            raise UserError(f"RAY_ADDRESS {address}: cannot connect to Ray: {root_line(error)}") from None
    _local_node_only()
    # Ray 2.60 turns token auth on for a new local cluster and says so with an opt-out hint: on is our default.
    logging.getLogger("ray._private.authentication.authentication_token_setup").setLevel(logging.ERROR)
    dashboard_port = _free_local_port()
    os.environ[API_SERVER_ENV] = f"http://{LOCALHOST}:{dashboard_port}"  # before ray.init: its workers inherit it
    try:
        context = ray.init(address="local", _node_ip_address=LOCALHOST, include_dashboard=True,
                           dashboard_host=LOCALHOST, dashboard_port=dashboard_port, log_to_driver=True)
    except Exception as error:  # also OSError (RAY_TMPDIR unusable) and the bare Exception of a node start-up timeout
        raise UserError(f"a local Ray instance could not start: {root_line(error)}") from None
    node_ip = ray.util.get_node_ip_address()
    if node_ip != LOCALHOST:  # a Ray release that resolves the address another way: never listen outside
        ray.shutdown()
        raise RuntimeError(f"the local Ray instance took node IP {node_ip}, not {LOCALHOST}: it would listen "
                           "beyond this machine")
    return context.dashboard_url or None

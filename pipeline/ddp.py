"""DDP rendezvous that stays on this machine when the training does.

Ray Train's torch backend meets its workers at a `torch.distributed.TCPStore` on worker 0, and the
store listens on every interface (torch binds the wildcard address; it has no option for another),
with no authentication: on a laptop's local Ray, anyone on the network could reach it. When worker 0's
node is the loopback node (a job's local Ray, `pipeline.cluster.connect`), every worker is on this
machine: `LoopbackTorchConfig` then meets them at a `FileStore` in the temp directory instead, and
points gloo's and NCCL's own sockets at the loopback interface. On a cluster (a routable node IP) it
is Ray's `TorchConfig` unchanged.

When a worker has died, shutting its process group down fails, and Ray logs that as a 20-line
`ActorDiedError` traceback from the controller; the backend says it in one line instead (the job then
prints where it resumed, `pipeline.train.train_func`).
"""

from __future__ import annotations

import ipaddress
import logging
import os
import tempfile
import uuid
from dataclasses import dataclass

import ray
from ray.exceptions import RayActorError, RayTaskError
from ray.train._internal.utils import get_address_and_port
from ray.train.torch.config import TorchConfig, _set_torch_distributed_env_vars, _setup_torch_process_group, _TorchBackend

from pipeline.cluster import LOCALHOST, root_line

logger = logging.getLogger(__name__)


def loopback_interface() -> str | None:
    """The name of the network interface that holds 127.0.0.1 (``lo`` on Linux, ``lo0`` on macOS)."""
    import psutil

    for name, addresses in psutil.net_if_addrs().items():
        if any(a.address == LOCALHOST for a in addresses):
            return name
    return None


def _use_loopback_sockets() -> None:
    """In a worker, before the process group: gloo's and NCCL's connections on the loopback interface."""
    name = loopback_interface()
    if name:
        os.environ["GLOO_SOCKET_IFNAME"] = name
        os.environ["NCCL_SOCKET_IFNAME"] = name


class _LoopbackTorchBackend(_TorchBackend):
    def on_shutdown(self, worker_group, backend_config: TorchConfig):
        try:
            super().on_shutdown(worker_group, backend_config)
        except (RayActorError, RayTaskError) as error:
            logger.warning(f"a training worker died ({root_line(error)[:200]}); Ray Train restarts the worker group")

    def on_start(self, worker_group, backend_config: TorchConfig):
        address, _ = worker_group.execute_single(0, get_address_and_port)
        if not ipaddress.ip_address(address).is_loopback:
            return super().on_start(worker_group, backend_config)
        store = os.path.join(tempfile.gettempdir(), f"aniformer-ddp-{uuid.uuid4().hex}")  # removed by the last rank
        worker_group.execute(_set_torch_distributed_env_vars)
        worker_group.execute(_use_loopback_sockets)
        ray.get([worker_group.execute_single_async(rank, _setup_torch_process_group, backend=backend_config.backend,
                                                   world_rank=rank, world_size=len(worker_group),
                                                   init_method=f"file://{store}", timeout_s=backend_config.timeout_s)
                 for rank in range(len(worker_group))])
        return None


@dataclass
class LoopbackTorchConfig(TorchConfig):
    """Ray's `TorchConfig`, with the rendezvous on this machine when the workers are (module doc)."""

    @property
    def backend_cls(self):
        return _LoopbackTorchBackend

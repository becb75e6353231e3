"""Ray for the `--backend ray` of eval and train: the one place that imports it (lazily), connects and sizes actors.

Ray is optional (`pip install 'drivesim[ray]'`): nothing imports this module until a ray backend is chosen, and then
a missing Ray is one line saying how to install it. A `RaySession` connects to a running cluster (`address`: "auto"
for the one `ray start` runs on this machine, or the head's host:port) or, without an address, starts Ray on this
machine for the command and stops it after. Every node must have drivesim installed and see the world, meshes and
policy files at the same paths as the driver (a shared file system); episodes and rollouts come back over Ray.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from types import ModuleType, TracebackType
from typing import Any

from drivesim.pipeline.errors import DrivesimError

INSTALL_HINT = "pip install 'drivesim[ray]'"
# Errors that mean "the worker (or its node) is gone", not "the code failed": its work is run again elsewhere.
LOST_WORKER_ERRORS = ("RayActorError", "ObjectLostError", "NodeDiedError", "WorkerCrashedError", "OwnerDiedError")


def import_ray() -> ModuleType:
    """The `ray` module, or a DrivesimError with one line saying how to install it."""
    try:
        import ray
    except ImportError as e:
        raise DrivesimError(
            f"--backend ray needs Ray, which is not installed; install it with `{INSTALL_HINT}` "
            "(or `pip install 'ray[default]>=2.40,<3'`)"
        ) from e
    return ray


class RaySession:
    """A connection to Ray held for a block of work; closing it disconnects (stopping a Ray it started here).

    :param address: "auto", the head's "host:port", or None: start Ray on this machine (or use $RAY_ADDRESS).
    """

    def __init__(self, address: str | None = None) -> None:
        self.address = address
        self.ray: ModuleType | None = None
        self._owns_connection = False

    def open(self) -> ModuleType:
        """Connect (or reuse the connection this process already has) and return the `ray` module."""
        ray = import_ray()
        if not ray.is_initialized():
            # "local" (not None) so that a stale /tmp/ray/ray_current_cluster is not mistaken for a running cluster.
            address = self.address or os.environ.get("RAY_ADDRESS") or "local"
            _check_reachable(address)
            options: dict[str, Any] = {"logging_level": logging.WARNING, "log_to_driver": False}
            if address == "local":
                options["include_dashboard"] = False
            try:
                ray.init(address=address, **options)
            except (ConnectionError, ValueError, RuntimeError) as e:
                first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise DrivesimError(f"cannot connect to the Ray cluster at {address}: {first[:200]}") from e
            self._owns_connection = True
        self.ray = ray
        return ray

    def close(self) -> None:
        """Disconnect (and stop a Ray started by this session); a connection made by the caller stays open."""
        if self.ray is not None and self._owns_connection and self.ray.is_initialized():
            self.ray.shutdown()
        self._owns_connection = False
        self.ray = None

    def __enter__(self) -> ModuleType:
        return self.open()

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """A host:port nobody listens on is one line now (Ray itself retries it for minutes before giving up)."""
    if address in ("local", "auto") or "://" in address or ":" not in address:
        return
    host, _, port = address.rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except (OSError, ValueError) as e:
        raise DrivesimError(
            f"no Ray cluster answers at {address} ({type(e).__name__}); start one with `ray start --head` "
            "there, or leave out --address to start Ray on this machine"
        ) from e


def cluster_cpus(ray: ModuleType) -> float:
    """CPUs of the connected cluster, all nodes together (at least 1)."""
    return max(float(ray.cluster_resources().get("CPU", 1.0)), 1.0)


def cpus_per_actor(ray: ModuleType, actors: int) -> float:
    """CPUs to reserve per actor so that `actors` of them fit on the cluster at once: 1, or a share of it."""
    share = cluster_cpus(ray) / max(actors, 1)
    return 1.0 if share >= 1.0 else max(int(share * 100) / 100, 0.01)


def is_lost_worker(error: BaseException) -> bool:
    """Whether `error` says a Ray worker or its node died (its work can run again elsewhere)."""
    return any(cls.__name__ in LOST_WORKER_ERRORS for cls in type(error).__mro__)


def get_or_lost(ray: ModuleType, ref: Any) -> tuple[Any, BaseException | None]:
    """A finished task's result, or (None, the error) when its worker or node died and the work can run again; the
    task's own DrivesimError (which Ray wraps) is raised as it is, any other error as Ray raised it."""
    try:
        return ray.get(ref), None
    except Exception as e:
        if not is_lost_worker(e):
            cause = getattr(e, "cause", None)
            if isinstance(cause, DrivesimError):
                raise cause from None
            raise
        return None, e


def kill_actors(ray: ModuleType, actors: list[Any]) -> None:
    """Stop actors for good (the dead and the never-started included)."""
    for actor in actors:
        with contextlib.suppress(Exception):  # already dead or never placed: nothing to stop
            ray.kill(actor, no_restart=True)

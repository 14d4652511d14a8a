"""Training, evaluation and offline estimation on a Ray cluster (``--ray ADDRESS``).

Ray is optional (``pip install tensegrity-gym[ray]``); nothing here imports it before
it is used. :mod:`agents.training.cluster.vec_env` is SB3's ``VecEnv`` over Ray actors; this
module says where the other heavy jobs run: in this process, or as Ray tasks.

Evaluation, offline estimation and the estimation benchmark each map one function over
independent jobs (an episode, a bag, a replay) through an :class:`Executor`: the local
one calls it job by job, the Ray one runs each job as a Ray task and gathers the
results in order. The function is the same either way, so a run on a cluster gives the
numbers the single-machine run gives for the same seeds.
"""

from __future__ import annotations

import contextlib
import logging
import socket
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator, Sequence
    from types import ModuleType

__all__ = [
    "INSTALL_HINT",
    "Executor",
    "LocalExecutor",
    "RayExecutor",
    "cluster_session",
    "executor",
    "require_ray",
]

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install tensegrity-gym[ray]"
CONNECT_TIMEOUT_S = 10.0
"""How long a cluster address may take to answer before it is refused (s)."""

T = TypeVar("T")
R = TypeVar("R")


class Executor(Protocol):
    """Maps a function over jobs; ``local`` says whether it runs in this process."""

    local: bool

    def map(self, fn: Callable[[T], R], jobs: Sequence[T]) -> list[R]:
        """``[fn(job) for job in jobs]``, in the order of ``jobs``."""
        ...


class LocalExecutor:
    """Every job in this process, one after the other."""

    local = True

    def map(self, fn: Callable[[T], R], jobs: Sequence[T]) -> list[R]:
        return [fn(job) for job in jobs]


def _apply(fn: Callable[[Any], Any], job: Any) -> Any:
    """The body of every Ray task: one job."""
    return fn(job)


class RayExecutor:
    """Every job as a Ray task of ``num_cpus`` CPUs, anywhere on the connected cluster;
    the function is sent once (``ray.put``), each job with its task."""

    local = False

    def __init__(self, num_cpus: float = 1.0) -> None:
        self.num_cpus = num_cpus

    def map(self, fn: Callable[[T], R], jobs: Sequence[T]) -> list[R]:
        ray = require_ray()
        task = ray.remote(num_cpus=self.num_cpus, max_retries=1)(_apply)
        shared = ray.put(fn)
        results: list[R] = ray.get([task.remote(shared, job) for job in jobs])
        return results


def require_ray() -> ModuleType:
    """The ``ray`` module, or an ImportError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ImportError(f"--ray needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def _check_reachable(address: str, timeout: float) -> None:
    """Refuse, within ``timeout`` seconds, a ``HOST:PORT`` (or ``ray://HOST:PORT``) that
    does not accept a connection; ``ray.init`` itself retries for minutes."""
    hostport = address.removeprefix("ray://")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(
            f"--ray {address!r}: expected HOST:PORT (the head's `ray start --head` port), "
            "'auto' (the cluster this machine joined) or 'local'"
        )
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as err:
        raise ConnectionError(
            f"cannot reach the Ray cluster at {address} within {timeout:g} s ({err}); "
            "is `ray start --head` running there? (--ray local starts one here)"
        ) from None


@contextlib.contextmanager
def cluster_session(address: str, timeout: float = CONNECT_TIMEOUT_S) -> Iterator[None]:
    """Connected to the Ray cluster at ``address`` for the ``with`` block: ``HOST:PORT``,
    ``ray://HOST:PORT``, ``auto`` or ``local`` (a Ray instance started here). Ray already
    initialised in this process is used as it is and left running; a session started
    here is shut down at the end."""
    ray = require_ray()
    if ray.is_initialized():
        yield
        return
    kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
    if address != "local":
        if address != "auto":
            _check_reachable(address, timeout)
        kwargs["address"] = address
    try:
        ray.init(**kwargs)
    except ConnectionError as err:  # 'auto' without a cluster on this machine
        raise ConnectionError(f"--ray {address}: {' '.join(str(err).split())}") from None
    resources = ray.cluster_resources()
    log.info(
        "Ray cluster at %s: %d nodes, %g CPUs",
        address,
        len([n for n in ray.nodes() if n["Alive"]]),
        resources.get("CPU", 0),
    )
    try:
        yield
    finally:
        ray.shutdown()


@contextlib.contextmanager
def executor(ray_address: str | None) -> Iterator[Executor]:
    """The local executor, or (``ray_address`` given) the Ray one for a
    :func:`cluster_session` that lasts the ``with`` block."""
    if ray_address is None:
        yield LocalExecutor()
        return
    with cluster_session(ray_address):
        yield RayExecutor()

"""``--backend ray``: one plain Ray task per trial (the only module that imports ``ray``).

Why tasks, not Ray Tune trials: a sweep here is a fixed grid with a fixed budget per trial (the
paper's protocol), so Tune's search algorithms and early-stopping schedulers have nothing to
do, while its experiment state, trial directories, retries and result logging would duplicate
ours (``OUT/sweep.json``, ``OUT/trials/<id>``, :mod:`.runner`) and put a second source of truth
beside them. A task runs exactly the function the local backend runs
(:func:`policies.sweep.trial.run_trial`), so both backends share every line of scheduling,
retrying, recording and reporting, and give the same per-trial results. Each task takes one
CPU (Ray sets ``OMP_NUM_THREADS=1`` in its worker), is never retried by Ray itself
(``max_retries=0``: the runner retries, attributing failures to the trial) and gets a fresh
worker process (``max_calls=1``), as a local trial does.

``--address auto`` (or ``HOST:PORT``) joins a running cluster (``ray start --head`` and
``ray start --address=...`` on the others, each with tupa installed in the same Python as
the driver's): the sweep directory must then be on a file system every node mounts at the same
path (a task on a node that does not see it fails saying so). Ray 2.59 and later authenticate
with a token: ``--address auto`` finds a cluster started on this machine with its token; for a
cluster elsewhere give its token as Ray reads it (``RAY_AUTH_TOKEN`` or
``RAY_AUTH_TOKEN_PATH``), or the connection fails, naming the address.
Without ``--address`` a private Ray instance starts on this machine with as many CPUs as it
has (or ``--workers``), listening on loopback only, without the dashboard, and stops with the
command (:func:`init_local_ray`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from collections.abc import Iterator
from typing import Any

from policies.sweep.backends import Outcome, machine_cores, one_line
from sim.errors import InputError

#: Ray's switch for single-machine instances (its default on Windows and macOS, where it does not
#: support clusters): "0" makes Ray's node address the loopback one.
SINGLE_MACHINE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


@contextlib.contextmanager
def _single_machine() -> Iterator[None]:
    """Ray in single-machine mode while a local instance starts.

    On Linux Ray deliberately replaces a loopback node address (``ray.init(_node_ip_address=
    "127.0.0.1")``, ``ray start --node-ip-address 127.0.0.1``) with the machine's network
    address, so that other nodes could join, and its GCS server, raylet, agents and workers
    listen there (and, in older Ray, on every interface). With clusters switched off
    (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``) the node address is the loopback one and every
    server binds to it. Ray reads that variable when it is imported, so the already imported
    constant is switched too; the processes Ray starts inherit the variable. Both are restored
    afterwards (the running instance keeps its address).
    """
    from ray._private import ray_constants

    saved_env = os.environ.get(SINGLE_MACHINE_ENV)
    saved_flag = getattr(ray_constants, "ENABLE_RAY_CLUSTER", None)
    os.environ[SINGLE_MACHINE_ENV] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        if saved_env is None:
            os.environ.pop(SINGLE_MACHINE_ENV, None)
        else:
            os.environ[SINGLE_MACHINE_ENV] = saved_env
        if saved_flag is None:
            with contextlib.suppress(AttributeError):
                del ray_constants.ENABLE_RAY_CLUSTER
        else:
            ray_constants.ENABLE_RAY_CLUSTER = saved_flag


def init_local_ray(num_cpus: int, logging_level: int = logging.WARNING) -> None:
    """Start a private Ray instance on this machine, listening on loopback only: ``num_cpus``
    CPUs, no dashboard, workers' output not sent to the driver. (``tests/policies`` starts its
    instances with it too.)"""
    import ray

    with _single_machine():
        ray.init(
            num_cpus=num_cpus,
            include_dashboard=False,
            _node_ip_address="127.0.0.1",
            logging_level=logging_level,
            log_to_driver=False,
        )


def _run(payload: dict[str, Any]) -> dict[str, Any]:
    from policies.sweep.trial import run_payload

    return run_payload(payload)


def _check_reachable(address: str) -> None:
    """A one-line error naming ``address`` when nothing listens there (fast, before Ray's own
    connection attempts, which wait for a minute)."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise InputError(f"--address: {address!r}: expected auto or HOST:PORT")
    try:
        with socket.create_connection((host, int(port)), timeout=5):
            pass
    except OSError as exc:
        raise InputError(
            f"--address: cannot reach a Ray cluster at {address}: {exc.strerror or exc}"
        ) from None


class RayBackend:
    """Trials as Ray tasks on a local instance or a cluster (see the module doc)."""

    name = "ray"

    def __init__(self, address: str | None = None, workers: int | None = None) -> None:
        import ray

        self._ray = ray
        self._owned = False
        if address and address != "auto":
            _check_reachable(address)
        if ray.is_initialized():
            pass  # a caller (a test, a notebook) started Ray: use it, leave it running
        elif address:
            try:
                ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
            except Exception as exc:
                raise InputError(
                    f"--address: cannot reach a Ray cluster at {address}: {one_line(exc)}"
                ) from None
        else:
            init_local_ray(workers or machine_cores())
            self._owned = True
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.slots = max(1, min(workers, cpus) if workers else cpus)
        self._address = address
        self._remote = ray.remote(num_cpus=1, max_retries=0, max_calls=1)(_run)
        self._refs: dict[Any, str] = {}

    def describe(self) -> str:
        where = f"cluster at {self._address}" if self._address else "local instance"
        return f"ray, {where}, {self.slots} CPU{'s' if self.slots > 1 else ''}"

    def submit(self, trial_id: str, payload: dict[str, Any]) -> None:
        self._refs[self._remote.remote(payload)] = trial_id

    def running(self) -> list[str]:
        return list(self._refs.values())

    def wait(self, timeout_s: float) -> list[tuple[str, Outcome]]:
        if not self._refs:
            return []
        ready, _ = self._ray.wait(list(self._refs), num_returns=1, timeout=timeout_s)
        if ready:
            ready, _ = self._ray.wait(list(self._refs), num_returns=len(self._refs), timeout=0)
        outcomes = []
        for ref in ready:
            trial_id = self._refs.pop(ref)
            outcomes.append((trial_id, self._outcome(ref)))
        return outcomes

    def _outcome(self, ref: Any) -> Outcome:
        exceptions = self._ray.exceptions
        try:
            return Outcome(result=self._ray.get(ref))
        except exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            return Outcome(error=one_line(cause) if cause is not None else one_line(exc))
        except (exceptions.WorkerCrashedError, exceptions.NodeDiedError) as exc:
            return Outcome(error=f"worker died ({type(exc).__name__})")
        except exceptions.RayError as exc:
            return Outcome(error=one_line(exc))

    def cancel_all(self) -> None:
        for ref in list(self._refs):
            # Already finished or gone: nothing to stop.
            with contextlib.suppress(Exception):
                self._ray.cancel(ref, force=True)
        self._refs.clear()

    def close(self) -> None:
        self.cancel_all()
        if self._owned and self._ray.is_initialized():
            self._ray.shutdown()

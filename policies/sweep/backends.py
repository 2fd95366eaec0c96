"""What the scheduler (:mod:`.runner`) needs of a backend, and the local one.

A backend runs trials (:func:`policies.sweep.trial.run_trial` payloads) at most ``slots`` at a
time and reports each one's :class:`Outcome` exactly once. A trial whose worker dies (killed,
out of memory, a lost node) is an outcome too, attributed to that trial alone.

:class:`LocalBackend` spawns one fresh process per trial (``multiprocessing``'s ``spawn``: no
state inherited from the driver, torch imported afresh on one thread), as many at once as the
machine has cores. One process per trial costs ~1-2 s of start-up, nothing beside a training
run, and gives every trial the same clean process a ``tupa train`` command would have; it also
means a dead worker takes only its own trial with it (a shared ``ProcessPoolExecutor`` breaks
every running trial when one worker dies). The workers ignore Ctrl-C: the driver stops them.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
import traceback
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, Protocol


@dataclass(frozen=True)
class Outcome:
    """How one attempt of a trial ended: ``result`` when it finished, ``error`` (one line)
    when it raised or its worker died."""

    result: dict[str, Any] | None = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


class Backend(Protocol):
    """Runs trials; see the module doc."""

    name: str
    slots: int

    def submit(self, trial_id: str, payload: dict[str, Any]) -> None: ...

    def running(self) -> list[str]: ...

    def wait(self, timeout_s: float) -> list[tuple[str, Outcome]]: ...

    def cancel_all(self) -> None: ...

    def close(self) -> None: ...

    def describe(self) -> str: ...


def machine_cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def one_line(exc: BaseException) -> str:
    """``Type: message`` on one line."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _exit_with_parent(parent_pid: int) -> None:
    """End this worker when the driver is gone (killed outright, no Ctrl-C to pass on): a
    resumed sweep reruns the trial, and an orphan must not keep writing into its directory."""
    while os.getppid() == parent_pid:
        time.sleep(1.0)
    os._exit(1)


def _worker_main(payload: dict[str, Any], conn: Connection) -> None:
    """A spawned worker: run the trial, send ("ok", result) or ("error", line, traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the driver stops us on Ctrl-C
    os.environ["OMP_NUM_THREADS"] = "1"
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), daemon=True).start()
    try:
        from policies.sweep.trial import run_payload

        result = run_payload(payload)
        conn.send(("ok", result))
    except BaseException as exc:
        conn.send(("error", one_line(exc), traceback.format_exc()))
    finally:
        conn.close()


class LocalBackend:
    """One spawned process per trial, ``workers`` at once (default: the machine's cores)."""

    name = "local"

    def __init__(self, workers: int | None = None) -> None:
        self.slots = workers or machine_cores()
        self._context = multiprocessing.get_context("spawn")
        self._running: dict[str, tuple[Any, Connection]] = {}
        self._messages: dict[str, tuple] = {}

    def describe(self) -> str:
        return f"local, {self.slots} worker process{'es' if self.slots > 1 else ''}"

    def submit(self, trial_id: str, payload: dict[str, Any]) -> None:
        receiver, sender = self._context.Pipe(duplex=False)
        process = self._context.Process(
            target=_worker_main, args=(payload, sender), name=f"tupa-trial-{trial_id}"
        )
        process.start()
        sender.close()
        self._running[trial_id] = (process, receiver)

    def running(self) -> list[str]:
        return list(self._running)

    def wait(self, timeout_s: float) -> list[tuple[str, Outcome]]:
        """Outcomes of trials that ended within ``timeout_s`` (possibly none)."""
        if not self._running:
            return []
        handles: dict[Any, str] = {}
        for trial_id, (process, receiver) in self._running.items():
            handles[process.sentinel] = trial_id
            if trial_id not in self._messages:
                handles[receiver] = trial_id
        ready = wait(list(handles), timeout=timeout_s)
        ended = []
        for handle in ready:
            trial_id = handles[handle]
            process, receiver = self._running[trial_id]
            if handle is receiver:
                try:
                    self._messages[trial_id] = receiver.recv()
                except (EOFError, OSError):
                    self._messages[trial_id] = ()
                continue
            ended.append(trial_id)
        outcomes = []
        for trial_id in ended:
            process, receiver = self._running.pop(trial_id)
            message = self._messages.pop(trial_id, None)
            if message is None and receiver.poll():
                try:
                    message = receiver.recv()
                except (EOFError, OSError):
                    message = None
            process.join()
            receiver.close()
            outcomes.append((trial_id, self._outcome(message, process.exitcode)))
        return outcomes

    @staticmethod
    def _outcome(message: tuple | None, exitcode: int | None) -> Outcome:
        if message and message[0] == "ok":
            return Outcome(result=message[1])
        if message and message[0] == "error":
            return Outcome(error=message[1])
        if exitcode is not None and exitcode < 0:
            try:
                name = signal.Signals(-exitcode).name
            except ValueError:
                name = f"signal {-exitcode}"
            return Outcome(error=f"worker died ({name})")
        return Outcome(error=f"worker died (exit code {exitcode}) without a result")

    def cancel_all(self) -> None:
        """Stop every running trial's process (SIGTERM, then SIGKILL after 5 s)."""
        for process, _ in self._running.values():
            if process.is_alive():
                process.terminate()
        for process, receiver in self._running.values():
            process.join(timeout=5)
            if process.is_alive():
                process.kill()
                process.join()
            receiver.close()
        self._running.clear()
        self._messages.clear()

    def close(self) -> None:
        self.cancel_all()

"""The native MAVSDK plumbing under :class:`~service.mavsdk_link.MavsdkLink`: connection URLs,
MAVSDK's log lines, and the lifetime of one MAVSDK instance (:class:`Session`).

* :func:`mavsdk_url` turns a pymavlink connection string into a MAVSDK URL.
* :func:`route_mavsdk_logs_to_python` sends MAVSDK's own log lines to the ``mavsdk`` logger: its
  callback (on MAVSDK's native threads) only queues a line, and a thread of ours logs it, so no
  logging handler ever runs on a MAVSDK thread.
* :class:`Session`: one MAVSDK instance, its connection and plugins, made and torn down safely.
  Tearing a session down (link loss, close) first waits, up to ``UNANSWERED_WAIT_S``, for MAVSDK
  to answer the asynchronous calls still in flight (an ``Offboard.start`` is asked for every
  ``mode_retry_s``), and keeps their ctypes callbacks alive until the instance is destroyed:
  destroying the plugins with a command in flight crashed the process natively (SIGSEGV inside
  the plugins' destroy; see ``benchmarks/mavsdk_link_loss.py``).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from service.vehicle_link import LinkConfig, mavlink

log = logging.getLogger(__name__)

UNANSWERED_WAIT_S = 3.0
"""How long closing a session waits for MAVSDK to answer the calls still open. MAVSDK answers an
unacknowledged command with a timeout after its own retries (3 tries by default); this bound is
meant to leave room for that, not to be reached."""

_MAVSDK_LOG_LEVELS = (logging.DEBUG, logging.DEBUG, logging.INFO, logging.WARNING)
"""MAVSDK's levels (debug, info, warn, err) one step down: it reports every failed connection
attempt as an error, and the link retries an unreachable vehicle for as long as it runs (its own
state says so)."""
_mavsdk_log_lines: queue.SimpleQueue[tuple[int, str, str | None, int]] = queue.SimpleQueue()
_log_thread: threading.Thread | None = None
_log_route_lock = threading.Lock()


def _queue_mavsdk_log_line(level: int, message: str, file: str | None, line: int) -> bool:
    """MAVSDK's log callback, called on MAVSDK's own native threads: only queues the line."""
    _mavsdk_log_lines.put((int(level), message, file, line))
    return True  # MAVSDK does not print it itself


def _log_mavsdk_lines() -> None:
    """The ``mavsdk-log`` thread: logs the queued lines to the ``mavsdk`` logger."""
    logger = logging.getLogger("mavsdk")
    while True:
        level, message, file, line = _mavsdk_log_lines.get()
        logger.log(_MAVSDK_LOG_LEVELS[min(max(level, 0), 3)], "%s (%s:%d)", message, file, line)


def route_mavsdk_logs_to_python() -> None:
    """Send MAVSDK's own log lines to the ``mavsdk`` Python logger instead of stdout.

    MAVSDK has one process-wide log callback; this installs ours only when nobody installed one
    (an application that subscribed its own keeps it). :meth:`MavsdkLink.start` calls it.
    MAVSDK calls the callback on its own threads, in the middle of its I/O and of its teardown;
    the callback only queues the line, and a daemon thread of ours hands it to ``logging``, so
    no logging handler (file or stream I/O, locks) ever runs on a MAVSDK thread.
    """
    import mavsdk.logging as mavsdk_logging

    global _log_thread
    with _log_route_lock:
        if getattr(mavsdk_logging, "_log_callback_ref", None) is not None:
            return
        if _log_thread is None:
            _log_thread = threading.Thread(target=_log_mavsdk_lines, name="mavsdk-log", daemon=True)
            _log_thread.start()
        mavsdk_logging.log_subscribe(_queue_mavsdk_log_line)


def mavsdk_url(url: str) -> str:
    """A MAVSDK connection URL for a pymavlink connection string (MAVSDK URLs pass through).

    ``tcp:H:P`` -> ``tcpout://H:P`` (client); ``tcpin:H:P`` -> ``tcpin://H:P`` (server);
    ``udpin:H:P`` and ``udp:H:P`` -> ``udpin://H:P``; ``udpout:H:P`` -> ``udpout://H:P``;
    a serial device ``/dev/ttyUSB0`` or ``/dev/ttyUSB0,921600`` -> ``serial:///dev/ttyUSB0:921600``
    (57600 baud when none is given). ValueError for anything else.
    """
    text = url.strip()
    if "://" in text:
        return text
    if text.startswith(("/", "COM")):
        device, _, baud = text.partition(",")
        baud = baud or "57600"
        if not baud.isdigit():
            raise ValueError(f"url: bad baud rate in {url!r}")
        return f"serial://{device}:{baud}"
    scheme, sep, rest = text.partition(":")
    schemes = {
        "tcp": "tcpout",
        "tcpout": "tcpout",
        "tcpin": "tcpin",
        "udp": "udpin",
        "udpin": "udpin",
        "udpout": "udpout",
    }
    host, _, port = rest.rpartition(":")
    if not sep or scheme.lower() not in schemes or not host or not port.isdigit():
        raise ValueError(
            f"url: expected tcp:HOST:PORT, udpin:HOST:PORT, udpout:HOST:PORT, a serial device "
            f"or a MAVSDK URL, got {url!r}"
        )
    return f"{schemes[scheme.lower()]}://{host}:{port}"


@dataclass
class Session:
    """One MAVSDK instance, its connection and (once the vehicle is found) its plugins."""

    sdk: Any
    opened_at: float
    system: Any = None
    system_id: int | None = None
    telemetry: Any = None
    action: Any = None
    offboard: Any = None
    direct: Any = None
    offboard_fed: bool = False
    """The Offboard plugin got a setpoint since it was made (so MAVSDK may be re-sending it)."""
    keep: list[Any] = field(default_factory=list)
    """Objects to ``destroy()`` after the instance (its Configuration)."""
    trampolines: list[Any] = field(default_factory=list)
    """The ctypes callbacks of asynchronous calls MAVSDK may still answer (a command waiting
    for its ACK or timeout). A plugin's ``destroy()`` drops its own, but MAVSDK's threads run
    until the instance itself is destroyed: a late answer into a dropped one is a native crash.
    Held here until then."""
    unanswered: int = 0
    """Asynchronous calls made through :meth:`call_async` that MAVSDK has not answered yet."""
    answered: threading.Condition = field(default_factory=threading.Condition)

    @classmethod
    def open(cls, url: str, config: LinkConfig, now: float) -> Session | None:
        """A MAVSDK instance connecting to ``url`` (a MAVSDK URL) with our ids and HEARTBEAT
        type from ``config``; None when MAVSDK refuses the connection (cannot bind, ...)."""
        from mavsdk import ComponentType, Configuration, Mavsdk

        component_type = (
            ComponentType.GROUND_STATION
            if config.heartbeat_type == mavlink.MAV_TYPE_GCS
            else ComponentType.COMPANION_COMPUTER
        )
        configuration = Configuration.create_with_component_type(component_type)
        configuration.system_id = config.source_system
        configuration.component_id = config.source_component
        sdk = Mavsdk(configuration)
        try:
            sdk.add_any_connection_with_handle(url)
        except Exception as exc:  # MAVSDK's ConnectionError: refused, cannot bind, ...
            log.debug("cannot open %s: %s", url, exc)
            sdk.destroy()
            configuration.destroy()
            return None
        return cls(sdk, now, keep=[configuration])

    def make_plugins(self, system: Any) -> None:
        """The plugins the link uses, for the autopilot ``system`` MAVSDK found."""
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.mavlink_direct import MavlinkDirect
        from mavsdk.plugins.offboard import Offboard
        from mavsdk.plugins.telemetry import Telemetry

        self.system = system
        self.system_id = system.get_system_id()
        self.telemetry = Telemetry(system)
        self.action = Action(system)
        self.offboard = Offboard(system)
        self.direct = MavlinkDirect(system)

    def renew_offboard(self) -> None:
        """A fresh Offboard plugin: ends MAVSDK's own re-sending of the last setpoint without a
        mode change (``Offboard.stop`` would also switch to Hold)."""
        from mavsdk.plugins.offboard import Offboard

        self.hold_callbacks(self.offboard)  # an Offboard.start may be pending
        self.offboard.destroy()
        self.offboard = Offboard(self.system)
        self.offboard_fed = False

    def close(self) -> None:
        """Tear the instance down once MAVSDK has answered the calls in flight (see the module
        docstring); no MAVSDK callback comes after it."""
        # Destroying a plugin whose command MAVSDK has not answered yet can crash MAVSDK when
        # the answer (or the timeout) comes: let them finish first.
        if not self.wait_answered(UNANSWERED_WAIT_S):
            log.debug("closing the MAVSDK session with %d calls unanswered", self.unanswered)
        for plugin in (self.telemetry, self.action, self.offboard, self.direct):
            self.hold_callbacks(plugin)
        with contextlib.suppress(Exception):
            self.sdk.destroy()  # joins MAVSDK's threads: no callback comes after it
        self.trampolines.clear()
        for item in self.keep:
            with contextlib.suppress(Exception):
                item.destroy()

    def hold_callbacks(self, plugin: Any) -> None:
        """Keep ``plugin``'s pending callbacks alive past its ``destroy()`` (see ``trampolines``;
        the binding keeps them in ``_callbacks``)."""
        self.trampolines.extend(getattr(plugin, "_callbacks", ()))

    def call_async(self, start: Callable[[Callable[..., None]], None], callback: Callable) -> None:
        """``start(answer)``: an asynchronous MAVSDK call whose answer goes to ``callback``,
        counted in ``unanswered`` until it comes (see :meth:`wait_answered`)."""
        once = threading.Lock()

        def answer(*args: Any) -> None:
            try:
                callback(*args)
            finally:
                if once.acquire(blocking=False):
                    self._answered_one()

        with self.answered:
            self.unanswered += 1
        try:
            start(answer)
        except BaseException:
            if once.acquire(blocking=False):
                self._answered_one()
            raise

    def _answered_one(self) -> None:
        with self.answered:
            self.unanswered -= 1
            self.answered.notify_all()

    def wait_answered(self, timeout_s: float) -> bool:
        """Wait until MAVSDK has answered every :meth:`call_async` (a command it gave up on is
        answered too, with a timeout), at most ``timeout_s``; False if some are still open."""
        with self.answered:
            return self.answered.wait_for(lambda: self.unanswered == 0, timeout_s)

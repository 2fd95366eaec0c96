"""A small thread-safe publish/subscribe hub whose publisher never waits for a subscriber.

The placement loop publishes one frame per decision period (:mod:`service.live_view`); each
open operator page is a :class:`Subscription` with a queue of at most ``max_frames`` frames.
:meth:`Hub.publish` appends to every queue under a lock held for microseconds and calls each
subscriber's ``notify`` (which must not block: the HTTP side passes
``loop.call_soon_threadsafe``). A subscriber that does not keep up loses its oldest frames,
counted in :attr:`Subscription.dropped`: memory per subscriber is bounded, and a slow or vanished
reader can never slow the publisher down. Frames are shared, not copied, between subscribers.

The hub takes at most ``max_subscribers`` at once (:class:`SubscriberLimitError` beyond), and
:meth:`Hub.close_all` ends every subscription (at shutdown: the readers see ``closed``).

    hub = Hub(max_subscribers=16)
    sub = hub.subscribe(notify=wake_reader)      # SubscriberLimitError when full
    hub.publish(frame)                           # from any thread, never blocks
    frames = sub.take()                          # everything queued, oldest first
    sub.close()
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")


class SubscriberLimitError(RuntimeError):
    """The hub already has ``max_subscribers`` subscribers."""


class Subscription(Generic[T]):
    """One subscriber's bounded queue (see the module docstring); made by :meth:`Hub.subscribe`."""

    def __init__(self, hub: Hub[T], max_frames: int, notify: Callable[[], None] | None) -> None:
        self._hub = hub
        self._frames: deque[T] = deque(maxlen=max_frames)
        self._notify = notify
        self.dropped = 0
        """Frames lost because this subscriber had ``max_frames`` waiting already."""
        self.closed = False

    def take(self) -> list[T]:
        """Every queued frame, oldest first (empty when none); the queue is emptied."""
        with self._hub._lock:
            frames = list(self._frames)
            self._frames.clear()
        return frames

    def pending(self) -> int:
        """How many frames wait in the queue (at most ``max_frames``)."""
        with self._hub._lock:
            return len(self._frames)

    def close(self) -> None:
        """Leave the hub (safe to call twice)."""
        self._hub._remove(self)


class Hub(Generic[T]):
    """Subscribers with bounded queues; publishing never blocks (see the module docstring)."""

    def __init__(self, max_subscribers: int = 16, max_frames: int = 4) -> None:
        if max_subscribers < 1 or max_frames < 1:
            raise ValueError("max_subscribers and max_frames must be at least 1")
        self.max_subscribers = max_subscribers
        self.max_frames = max_frames
        self._lock = threading.Lock()
        self._subscribers: list[Subscription[T]] = []
        self.published = 0
        self.dropped = 0
        """Frames lost over every subscriber, past and present."""

    def subscribe(self, notify: Callable[[], None] | None = None) -> Subscription[T]:
        """A new subscription; ``notify()`` is called after each publish (from the publisher's
        thread: it must return at once). :class:`SubscriberLimitError` when the hub is full."""
        with self._lock:
            if len(self._subscribers) >= self.max_subscribers:
                raise SubscriberLimitError(
                    f"live view: {self.max_subscribers} streams open already (the limit)"
                )
            subscription = Subscription(self, self.max_frames, notify)
            self._subscribers.append(subscription)
        return subscription

    def publish(self, frame: T) -> None:
        """Queue ``frame`` for every subscriber (dropping each one's oldest when full) and
        notify them. Never blocks and never raises on a subscriber's account."""
        with self._lock:
            self.published += 1
            subscribers = list(self._subscribers)
            for subscription in subscribers:
                if len(subscription._frames) == self.max_frames:
                    subscription.dropped += 1
                    self.dropped += 1
                subscription._frames.append(frame)
        for subscription in subscribers:
            _notify(subscription)

    def close_all(self) -> None:
        """End every subscription (each is told through ``notify``); new ones may follow."""
        with self._lock:
            subscribers, self._subscribers = self._subscribers, []
            for subscription in subscribers:
                subscription.closed = True
        for subscription in subscribers:
            _notify(subscription)

    def __len__(self) -> int:
        with self._lock:
            return len(self._subscribers)

    def _remove(self, subscription: Subscription[T]) -> None:
        with self._lock:
            subscription.closed = True
            subscription._frames.clear()
            if subscription in self._subscribers:
                self._subscribers.remove(subscription)


def _notify(subscription: Subscription[T]) -> None:
    if subscription._notify is None:
        return
    try:
        subscription._notify()
    except Exception as exc:  # e.g. the reader's event loop has closed: its stream is over
        log.debug("live view: a subscriber could not be notified: %s", exc)

"""Progress of a long run on standard error: how far it is, and how long it has left.

:class:`Progress` counts items (episodes, scenarios) towards a total. On a terminal it is a tqdm
bar (rate and ETA); anywhere else (a log file, ``docker logs``, ``journalctl``, a pipe), where a
bar would be one endless line of carriage returns, it writes a plain line every
``interval_s`` seconds, with the time left, and one when it closes::

    ddqn-gen10k: 120/2000 ep (6 %), utility 0.712; 4.1 min elapsed, about 58 min left
    ddqn-gen10k: 2000/2000 ep in 62 min

The time left is the items still to do times the mean time of the items done since the
progress started (items counted as done before it, ``initial``, a resumed run's, are not
timed). :func:`format_duration` writes durations for people.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

LINE_INTERVAL_S = 30.0
"""Seconds between two progress lines where there is no terminal."""


def format_duration(seconds: float) -> str:
    """``45 s``, ``3.5 min``, ``58 min``, ``2 h 05 min``: as precise as a person needs."""
    seconds = max(float(seconds), 0.0)
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = seconds / 60
    if minutes < 10:
        return f"{minutes:.1f} min"
    if minutes < 90:
        return f"{minutes:.0f} min"
    hours, minutes = divmod(round(minutes), 60)
    return f"{hours} h {minutes:02d} min"


class Progress:
    """Items done out of ``total``, shown on ``stream`` (standard error by default).

    ``bar``: a tqdm bar (True), plain lines every ``interval_s`` (False), or a bar only when
    ``stream`` is a terminal (None, the default). ``clock`` is :func:`time.monotonic` unless a
    test gives another. :meth:`write` prints a line without breaking the bar; :meth:`close`
    ends it (a last line without a terminal). ``enabled=False`` shows nothing at all.
    """

    def __init__(
        self,
        total: int,
        desc: str,
        unit: str,
        *,
        initial: int = 0,
        stream: TextIO | None = None,
        bar: bool | None = None,
        interval_s: float = LINE_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
        enabled: bool = True,
    ) -> None:
        self.total, self.desc, self.unit = total, desc, unit
        self.n = self.initial = initial
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.interval_s = interval_s
        self.clock = clock
        self.started = self._last_line = clock()
        self.postfix: dict[str, str] = {}
        self._bar: Any = None
        if enabled and (bar if bar is not None else _is_terminal(self.stream)):
            from tqdm import tqdm

            self._bar = tqdm(
                total=total,
                initial=initial,
                desc=desc,
                unit=unit,
                file=self.stream,
                dynamic_ncols=True,
            )

    def elapsed_s(self) -> float:
        return self.clock() - self.started

    def left_s(self) -> float | None:
        """Seconds left at the pace of the items done so far; None before the first one."""
        done = self.n - self.initial
        if done <= 0:
            return None
        return max(self.total - self.n, 0) * self.elapsed_s() / done

    def update(self, n: int = 1, **postfix: str) -> None:
        """``n`` more items done; ``postfix`` (e.g. ``utility="0.712"``) is shown beside."""
        self.n += n
        self.postfix.update(postfix)
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.update(n)
            if postfix:
                self._bar.set_postfix(self.postfix, refresh=False)
            return
        now = self.clock()
        if now - self._last_line >= self.interval_s:
            self._last_line = now
            self._print(self.line())

    def line(self) -> str:
        """Where the run is: done/total, the postfix, elapsed time and time left."""
        percent = f" ({100 * self.n / self.total:.0f} %)" if self.total else ""
        extra = "".join(f", {k} {v}" for k, v in self.postfix.items())
        left = self.left_s()
        eta = f", about {format_duration(left)} left" if left is not None else ""
        elapsed = format_duration(self.elapsed_s())
        done = f"{self.desc}: {self.n}/{self.total} {self.unit}{percent}{extra}"
        return f"{done}; {elapsed} elapsed{eta}"

    def write(self, line: str) -> None:
        """One line of text, above the bar on a terminal."""
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.write(line, file=self.stream)
        else:
            self._print(line)

    def close(self) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        else:
            extra = "".join(f", {k} {v}" for k, v in self.postfix.items())
            self._print(
                f"{self.desc}: {self.n}/{self.total} {self.unit}{extra} in "
                f"{format_duration(self.elapsed_s())}"
            )
        self.enabled = False

    def _print(self, line: str) -> None:
        print(line, file=self.stream, flush=True)


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # no isatty, or closed
        return False

"""Progress reports that stay readable: a tqdm bar on a terminal, plain lines in a log.

A tqdm bar redraws itself with carriage returns; written to a file or a pipe (a cluster job's log,
``2> run.log``) every redraw becomes bytes of its own, and long jobs leave megabytes of them.
`progress_bar` therefore gives tqdm only when its stream is a terminal; elsewhere a `LineProgress`
writes one newline-terminated line at most every ``interval_s`` seconds (and one at the end) with
the count, the total, the rate and the time left. Both have tqdm's everyday interface (iteration,
``update``, ``set_postfix``, ``set_description``, ``close``, a context manager).

This module imports no jax and nothing of the package: every layer may use it.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import IO, Any

# Seconds between two lines of a `LineProgress`: a line every 10 s keeps an hour-long job's log
# at a few hundred lines while still showing that it moves.
DEFAULT_INTERVAL_S = 10.0


def progress_bar(
    iterable: Iterable | None = None,
    *,
    total: float | None = None,
    desc: str | None = None,
    unit: str = "it",
    disable: bool = False,
    file: IO[str] | None = None,
    interval_s: float = DEFAULT_INTERVAL_S,
    clock: Callable[[], float] = time.monotonic,
    **tqdm_kwargs: Any,
):
    """A progress bar for ``file`` (default stderr): tqdm on a terminal, `LineProgress` elsewhere.

    Args:
      iterable: optional iterable to wrap (as tqdm's first argument).
      total: expected number of units (None: ``len(iterable)`` when it has one, else unknown).
      desc: a short name of the work, printed first.
      unit: the unit counted ("frame", "step", ...).
      disable: report nothing (iteration and updates still work).
      file: the stream; its ``isatty()`` decides between the two kinds.
      interval_s: seconds between lines when not a terminal.
      clock: the time function of the line reports (seconds; tests give a fake one).
      **tqdm_kwargs: passed to tqdm on a terminal (``leave``, ``dynamic_ncols``, ...); of them,
        the line reports use ``initial`` only.
    Returns:
      a ``tqdm.auto.tqdm`` or a `LineProgress`.
    """
    stream = sys.stderr if file is None else file
    if stream is None:  # no stderr at all (pythonw, some daemons): nowhere to report
        disable = True
    if _is_terminal(stream):
        from tqdm.auto import tqdm

        return tqdm(
            iterable, total=total, desc=desc, unit=unit, disable=disable, file=file, **tqdm_kwargs
        )
    return LineProgress(
        iterable,
        total=total,
        desc=desc,
        unit=unit,
        disable=disable,
        file=stream,
        interval_s=interval_s,
        clock=clock,
        initial=tqdm_kwargs.get("initial", 0),
    )


class LineProgress:
    """Progress as plain lines, at most one per ``interval_s`` seconds and one at the end.

    A line reads ``desc: 120/500 frame (24%), 35.2 frame/s, 0:10 elapsed, 0:11 left, loss=0.3``
    (no total: no percentage and no time left). Arguments as `progress_bar`'s.
    """

    def __init__(
        self,
        iterable: Iterable | None = None,
        *,
        total: float | None = None,
        desc: str | None = None,
        unit: str = "it",
        disable: bool = False,
        file: IO[str] | None = None,
        interval_s: float = DEFAULT_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
        initial: float = 0,
    ):
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.iterable = iterable
        self.total = total
        self.desc = desc
        self.unit = unit
        self.file = sys.stderr if file is None else file
        self.disable = disable or self.file is None
        self.interval_s = interval_s
        self.n = initial
        self.postfix = ""
        self._clock = clock
        self._initial = initial
        self._start = clock()
        self._last_line = self._start
        self._last_said: tuple | None = None  # (count, postfix) of the last line written
        self._closed = False

    def __iter__(self) -> Iterator:
        if self.iterable is None:
            raise TypeError("LineProgress made without an iterable is not iterable")
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __len__(self) -> int:
        return int(self.total or 0)

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, n: float = 1) -> None:
        """Adds ``n`` units; writes a line when ``interval_s`` has passed since the last one."""
        self.n += n
        now = self._clock()
        if now - self._last_line >= self.interval_s:
            self._write(now)

    def set_postfix(self, ordered_dict: dict | None = None, refresh: bool = True, **kwargs) -> None:
        """Values shown at the end of the next line (``key=value``, as tqdm)."""
        items = {**(ordered_dict or {}), **kwargs}
        self.postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = str(s)

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        self.desc = desc

    def refresh(self) -> None:
        """Writes a line now."""
        self._write(self._clock())

    def close(self) -> None:
        """Writes the final line (once; not when the last line said the same)."""
        if self._closed:
            return
        self._closed = True
        if self._last_said != (self.n, self.postfix):
            self._write(self._clock())

    def line(self, now: float) -> str:
        """The report at time ``now`` (seconds of ``clock``), without the newline."""
        elapsed = max(now - self._start, 0.0)
        done = self.n - self._initial
        rate = done / elapsed if elapsed > 0 else None
        parts = [f"{_number(self.n)}/{_number(self.total)}" if self.total else _number(self.n)]
        parts[0] += f" {self.unit}"
        if self.total:
            parts[0] += f" ({100.0 * self.n / self.total:.0f}%)"
        parts.append(f"{_rate(rate)} {self.unit}/s")
        parts.append(f"{_clock_time(elapsed)} elapsed")
        if self.total and rate:
            parts.append(f"{_clock_time(max(self.total - self.n, 0) / rate)} left")
        if self.postfix:
            parts.append(self.postfix)
        head = f"{self.desc}: " if self.desc else ""
        return head + ", ".join(parts)

    def _write(self, now: float) -> None:
        self._last_line, self._last_said = now, (self.n, self.postfix)
        if self.disable:
            return
        self.file.write(self.line(now) + "\n")
        self.file.flush()


def _is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def _number(x: float | None) -> str:
    if x is None:
        return "?"
    return str(int(x)) if float(x).is_integer() else f"{x:.4g}"


def _rate(rate: float | None) -> str:
    """Three significant digits, never in exponent form (1520, 35.2, 0.0417)."""
    if rate is None:
        return "?"
    return f"{rate:.0f}" if rate >= 100 else f"{rate:.3g}"


def _clock_time(seconds: float) -> str:
    """``m:ss`` or ``h:mm:ss``."""
    s = int(round(seconds))
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"

"""Progress of a long run: stage k/n, step k/n, load factor, elapsed and estimated time left.

:class:`Progress` is fed the converged steps of a load path (``step``) and logs one line
at INFO (the CLI's default level) at most every ``interval`` seconds; while a step takes
longer (Newton iterations, step cuts), a background heartbeat logs every ``interval``
seconds what is being worked on, so a run is never silent for long. The estimate of the
time left assumes the remaining nominal steps take as long, on average, as the ones done
so far. Messages hold numbers only (no arrays). No dependency: plain ``logging``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence

log = logging.getLogger(__name__)


def _duration(seconds: float) -> str:
    """'42 s', '3 min 05 s' or '1 h 02 min'."""
    s = round(max(seconds, 0.0))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def _beating(beat: Callable[[], None], interval: float, stop: threading.Event,
             name: str) -> threading.Thread:
    """A started daemon thread calling ``beat`` every interval / 2 seconds until ``stop``
    is set (it never keeps the process alive)."""
    stop.clear()

    def run():
        while not stop.wait(interval / 2):
            beat()

    thread = threading.Thread(target=run, name=name, daemon=True)
    thread.start()
    return thread


class Progress:
    """Progress of a load path of stages (objects with ``name`` and ``n_steps``).

    Args:
      stages: the load path's stages.
      completed: stages already done (a resumed run).
      interval: seconds between progress lines, and of the heartbeat, s.
      clock: the time source (seconds), for tests.
      logger: where to log (INFO).

    Use as a context manager (starts and stops the heartbeat thread), or call
    :meth:`start` and :meth:`close`.
    """

    def __init__(self, stages: Sequence, completed: int = 0, *, interval: float = 15.0,
                 clock: Callable[[], float] = time.monotonic, logger=log):
        self.names = [s.name for s in stages]
        self.n_steps = [max(int(s.n_steps), 1) for s in stages]
        self.interval, self.clock, self.log = float(interval), clock, logger
        self.stage, self.step_no, self.t = completed, 0, 0.0
        self.start_done = self.fraction()
        self.t0 = self.last_line = self.last_step = clock()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def fraction(self) -> float:
        """Fraction of the nominal load steps of the whole path done, in [0, 1]."""
        total = sum(self.n_steps)
        done = sum(self.n_steps[: self.stage])
        if self.stage < len(self.n_steps):
            done += self.t * self.n_steps[self.stage]
        return min(done / total, 1.0) if total else 1.0

    def remaining_s(self) -> float | None:
        """Estimated seconds left (None before any step of this run)."""
        done = self.fraction() - self.start_done
        if done <= 0:
            return None
        return (self.clock() - self.t0) * (1.0 - self.fraction()) / done

    def message(self) -> str:
        """'stage 2/3 tighten, step 3/4, t = 0.750, 58% done, 1 min 10 s elapsed, about
        50 s left'."""
        k = min(self.stage, len(self.names) - 1)
        left = self.remaining_s()
        return (f"stage {k + 1}/{len(self.names)} {self.names[k]}, step {self.step_no}/"
                f"{self.n_steps[k]}, t = {self.t:.3f}, {100 * self.fraction():.0f}% done, "
                f"{_duration(self.clock() - self.t0)} elapsed"
                + ("" if left is None else f", about {_duration(left)} left"))

    def step(self, stage: str, step: int, t: float) -> None:
        """A step of stage ``stage`` (name) converged at load factor t: log the progress if
        the last line is ``interval`` seconds old or the stage is complete."""
        with self._lock:
            later = [i for i, n in enumerate(self.names) if n == stage and i >= self.stage]
            self.stage = later[0] if later else self.names.index(stage)
            self.step_no, self.t = int(step), float(t)
            now = self.last_step = self.clock()
            if now - self.last_line >= self.interval or self.t >= 1.0 - 1e-12:
                self.last_line = now
                self.log.info("progress: %s", self.message())
            if self.t >= 1.0 - 1e-12:  # the next stage starts at t = 0
                self.stage, self.step_no, self.t = self.stage + 1, 0, 0.0

    def beat(self) -> None:
        """Log what is being worked on if nothing was logged, and no step converged, for
        ``interval`` seconds."""
        with self._lock:
            now = self.clock()
            if (min(now - self.last_line, now - self.last_step) < self.interval
                    or self.stage >= len(self.names)):
                return
            self.last_line = now
            self.log.info("progress: %s; step %d under way for %s", self.message(),
                          self.step_no + 1, _duration(now - self.last_step))

    def start(self) -> Progress:
        """Start the heartbeat thread (a daemon: it never keeps the process alive)."""
        if self._thread is None and self.interval > 0:
            self._thread = _beating(self.beat, self.interval, self._stop, "eyefem-progress")
        return self

    def close(self) -> None:
        """Stop the heartbeat."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def __enter__(self) -> Progress:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


class Heartbeat:
    """Log ``what()`` with the time since the last news every ``interval`` seconds while
    there is no news (:meth:`news`): a long computation that reports only when a piece
    ends (a planner's simulation) is never silent for long.

    Args:
      what: the message's subject, called at each beat (e.g. lambda: "simulation 3").
      interval: seconds between beats, s (0: none).
      clock, logger: as :class:`Progress`.
    """

    def __init__(self, what: Callable[[], str], *, interval: float = 30.0,
                 clock: Callable[[], float] = time.monotonic, logger=log):
        self.what, self.interval, self.clock, self.log = what, float(interval), clock, logger
        self.last_news = self.last_line = clock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def news(self) -> None:
        """Something was reported: the next beat is ``interval`` seconds from now."""
        self.last_news = self.last_line = self.clock()

    def beat(self) -> None:
        """Log '<what> under way for <time>' if nothing was said for ``interval`` s."""
        now = self.clock()
        if now - self.last_line >= self.interval:
            self.last_line = now
            self.log.info("%s under way for %s", self.what(), _duration(now - self.last_news))

    def __enter__(self) -> Heartbeat:
        if self._thread is None and self.interval > 0:
            self._thread = _beating(self.beat, self.interval, self._stop, "eyefem-heartbeat")
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

"""How many threads a view's parallel kernels use at a call (`ViewConfig.render_threads` is the most they may use).

A parallel kernel call at the policy's resolution lasts well under a millisecond, so a pool thread that has to wait for
a core held by another process costs far more than the call itself: a second thread pays off only while a core is
free. `usable_threads` therefore grants at most the cores this process may run on (its affinity) minus the CPU time
other processes took on them over the last fraction of a second (re-measured at most every `RECHECK_S`); below two
free cores the caller runs the serial kernels, with the same pixels.

numba's threading layer is set to `workqueue` unless the user chose one (`NUMBA_THREADING_LAYER`): its pool threads
sleep between calls, where the OpenMP layer's spin on a core for milliseconds after each call, taking it from the
calling thread and from other processes on a busy machine; it also keeps numba's pool apart from torch's OpenMP one.
The workqueue layer does not take concurrent launches, so `parallel_slot` admits one parallel call at a time and
sends the others to the serial kernels. A free core is still no promise that threads pay off at a small view (a pool
thread's wake-up can cost more than its share of the work): `governed_threads` also times both kinds of call at each
view call site and keeps to the faster (`PayOff`).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import psutil

RECHECK_S = 0.25
"""Seconds between two measurements of the free cores (one reading of the CPU counters each)."""
FREE_MARGIN = 0.25
"""Share of a core other processes may still use of each core counted free (their short bursts)."""


def _cpu_set() -> list[int]:
    """The CPUs this process may run on (all of them where affinity is unknown)."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def busy_seconds(cpus: list[int]) -> float:
    """CPU seconds spent not idle so far on the CPUs `cpus`, by all processes (steal time counted busy)."""
    if len(cpus) >= (psutil.cpu_count() or 1):
        times = [psutil.cpu_times()]
    else:
        every = psutil.cpu_times(percpu=True)
        times = [every[c] for c in cpus if c < len(every)]
    busy = 0.0
    for t in times:
        idle = t.idle + getattr(t, "iowait", 0.0)
        guests = getattr(t, "guest", 0.0) + getattr(t, "guest_nice", 0.0)  # already inside user and nice
        busy += sum(t) - guests - idle
    return busy


class FreeCores:
    """The free cores of this process's CPUs, measured over the time between two checks.

    :param cpus: the CPUs this process may run on. :param clock: seconds (monotonic).
    :param busy: CPU seconds all processes spent on `cpus` so far (`busy_seconds`).
    :param own: CPU seconds this process spent so far, all its threads.
    """

    def __init__(
        self,
        cpus: list[int] | None = None,
        clock: Callable[[], float] = time.monotonic,
        busy: Callable[[list[int]], float] = busy_seconds,
        own: Callable[[], float] = time.process_time,
    ) -> None:
        self.cpus = _cpu_set() if cpus is None else list(cpus)
        self._clock, self._busy, self._own = clock, busy, own
        self._sample: tuple[float, float, float] | None = None
        self.free = 0.0  # unknown until two samples exist: no second thread before that
        self._lock = threading.Lock()

    def measure(self) -> float:
        """The free cores (0 to len(cpus)): the CPUs' count less what other processes used since the previous
        sample, re-measured only when `RECHECK_S` has passed (else the last figure, without reading a counter)."""
        now = self._clock()
        if self._sample is not None and now - self._sample[0] < RECHECK_S:
            return self.free
        with self._lock:
            sample = (now, self._busy(self.cpus), self._own())
            if self._sample is not None and sample[0] > self._sample[0]:
                wall_s = sample[0] - self._sample[0]
                others_s = max((sample[1] - self._sample[1]) - (sample[2] - self._sample[2]), 0.0)
                self.free = max(len(self.cpus) - others_s / wall_s, 0.0)
            self._sample = sample
        return self.free

    def threads(self, requested: int) -> int:
        """How many of `requested` threads to use now: no more than the CPUs, nor than the free cores (each may be
        `FREE_MARGIN` used by others); 1 means the serial kernels."""
        if requested <= 1 or len(self.cpus) <= 1:
            return 1
        free = int(self.measure() + FREE_MARGIN)
        return max(1, min(requested, len(self.cpus), free))


_FREE = FreeCores()
_PARALLEL = threading.Lock()
_forced: int | None = None


def usable_threads(requested: int) -> int:
    """How many of `requested` threads a view's parallel kernels should use at this call (1: the serial kernels)."""
    if requested <= 1:
        return 1
    if _forced is not None:
        return min(requested, _forced)
    return _FREE.threads(requested)


@contextmanager
def exact_threads() -> Iterator[None]:
    """Within it, `usable_threads` grants every requested thread whatever the load (pixel tests of the parallel
    kernels, and benchmarks of the ungoverned parallel path)."""
    global _forced
    before, _forced = _forced, 1 << 16
    try:
        yield
    finally:
        _forced = before


class PayOff:
    """Whether a call site's kernels have run faster on threads than on one, from the durations of both kinds of call
    (a moving average each): the faster kind is chosen, the other still timed once every `EXPLORE_EVERY` calls."""

    def __init__(self) -> None:
        self.seconds: dict[bool, float] = {}  # parallel? -> average seconds per call
        self.calls = 0

    def parallel(self) -> bool:
        """Whether the next call should run on threads."""
        self.calls += 1
        if False not in self.seconds:
            return False
        if True not in self.seconds:
            return True
        faster = self.seconds[True] < self.seconds[False]
        return faster != (self.calls % EXPLORE_EVERY == 0)

    def record(self, parallel: bool, seconds: float) -> None:
        """Add one call's duration to its kind's average."""
        last = self.seconds.get(parallel)
        self.seconds[parallel] = seconds if last is None else last + AVERAGE_WEIGHT * (seconds - last)


EXPLORE_EVERY = 32
"""A call site whose kernels run faster one way still times the other way once in this many calls."""
AVERAGE_WEIGHT = 0.2
"""Weight of a new duration in its kind's moving average."""
_PAYOFF: dict[str, PayOff] = {}


@contextmanager
def governed_threads(requested: int, site: str) -> Iterator[int]:
    """The thread count a view's kernel call at call site `site` should use (1: the serial kernels): at most the
    free cores (`usable_threads`), and 1 where the site's calls have run faster on one thread (`PayOff`, unless
    `exact_threads`). The call's duration is recorded."""
    threads = usable_threads(requested)
    if threads <= 1 or _forced is not None:
        yield threads
        return
    payoff = _PAYOFF.setdefault(site, PayOff())
    parallel = payoff.parallel()
    start = time.perf_counter()
    yield threads if parallel else 1
    payoff.record(parallel, time.perf_counter() - start)


@contextmanager
def parallel_slot(threads: int) -> Iterator[int]:
    """The thread count a parallel kernel call may run with: `threads`, numba's pool set to it, or 1 (run the serial
    kernel) where `threads` is 1 or another thread's parallel call is under way."""
    if threads <= 1 or not _PARALLEL.acquire(blocking=False):
        yield 1
        return
    try:
        _use_layer()
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        yield threads
    finally:
        _PARALLEL.release()


def _use_layer() -> None:
    """Choose numba's `workqueue` threading layer unless the user set one (only before numba's first parallel call
    in the process starts a layer; afterwards this changes nothing)."""
    import numba

    if "NUMBA_THREADING_LAYER" not in os.environ and numba.config.THREADING_LAYER == "default":
        numba.config.THREADING_LAYER = "workqueue"

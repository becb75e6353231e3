"""`render_threads` on a busy machine: the thread count a view call is granted from the free cores
(`sim/cpu_threads.py`), one parallel launch at a time, and the same observations on one thread, on two threads
granted on every call, and on two threads requested while the machine is busy."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from sim_worlds import SMALL_VIEW, write_test_world

import drivesim.sim.envs  # noqa: F401  (registers the envs)
from drivesim.sim import cpu_threads, fill_kernel, raster_kernel, warp_kernel
from drivesim.sim.cpu_threads import FreeCores, PayOff, busy_seconds, exact_threads, parallel_slot


class FakeMachine:
    """CPU counters of a machine whose other processes use `others_cores` cores and this one `own_cores`."""

    def __init__(self, others_cores: float, own_cores: float = 1.0) -> None:
        self.others_cores, self.own_cores = others_cores, own_cores
        self.now_s, self.busy_s, self.own_s, self.reads = 0.0, 0.0, 0.0, 0

    def advance(self, seconds: float) -> None:
        self.now_s += seconds
        self.busy_s += (self.others_cores + self.own_cores) * seconds
        self.own_s += self.own_cores * seconds

    def busy(self, cpus: list[int]) -> float:
        self.reads += 1
        return self.busy_s

    def own(self) -> float:
        return self.own_s

    def cores(self, cpus: int = 2) -> FreeCores:
        return FreeCores(list(range(cpus)), clock=lambda: self.now_s, busy=self.busy, own=self.own)


def _granted(machine: FakeMachine, cores: FreeCores, requested: int = 2) -> int:
    cores.threads(requested)  # the first sample
    machine.advance(1.0)
    return cores.threads(requested)


@pytest.mark.parametrize(
    ("others_cores", "cpus", "requested", "expected"),
    [
        (0.05, 2, 2, 2),  # a quiet 2-core machine: both cores
        (1.0, 2, 2, 1),  # a second process keeps one core busy: the serial kernels
        (1.9, 2, 2, 1),  # load ~8 on 2 cores, this process's own share subtracted
        (0.6, 2, 2, 1),  # more than FREE_MARGIN of the second core taken
        (0.05, 2, 4, 2),  # never more threads than CPUs
        (1.0, 4, 4, 3),  # 4 CPUs, one busy: three threads
        (0.0, 1, 2, 1),  # one CPU allowed (affinity)
        (0.0, 2, 1, 1),  # one thread asked for
    ],
)
def test_threads_follow_the_free_cores(others_cores: float, cpus: int, requested: int, expected: int) -> None:
    machine = FakeMachine(others_cores)
    assert _granted(machine, machine.cores(cpus), requested) == expected


def test_no_second_thread_before_a_measurement_and_counters_read_sparingly() -> None:
    machine = FakeMachine(0.0)
    cores = machine.cores()
    assert cores.threads(2) == 1, "one sample is no measurement: the serial kernels until a second one"
    machine.advance(1.0)
    assert cores.threads(2) == 2
    reads = machine.reads
    machine.others_cores = 1.0  # the machine turns busy; within RECHECK_S the last figure holds
    for _ in range(100):
        machine.advance(cpu_threads.RECHECK_S / 1000)
        cores.threads(2)
    assert machine.reads == reads, "the CPU counters are read at most once per RECHECK_S"
    machine.advance(cpu_threads.RECHECK_S)
    assert cores.threads(2) == 1, "after RECHECK_S the busy core is seen"
    assert cores.free == pytest.approx(1.0)


def test_busy_seconds_counts_this_process_cpu_time() -> None:
    cpus = sorted(cpu_threads._cpu_set())
    busy_before, own_before = busy_seconds(cpus), time.process_time()
    end = time.perf_counter() + 0.2
    while time.perf_counter() < end:
        pass
    own_s = time.process_time() - own_before
    # The kernel's counters tick at 1/100 s: this process's spin is inside the busy time of its CPUs.
    assert busy_seconds(cpus) - busy_before >= own_s - 0.03 > 0


def test_payoff_keeps_to_the_faster_kind_and_still_times_the_other() -> None:
    payoff = PayOff()
    assert payoff.parallel() is False, "one serial call first"
    payoff.record(False, 1.0e-3)
    assert payoff.parallel() is True, "then one parallel call"
    payoff.record(True, 3.0e-3)  # threads slower: a busy or small view
    choices = []
    for _ in range(3 * cpu_threads.EXPLORE_EVERY):
        choices.append(payoff.parallel())
        payoff.record(choices[-1], 3.0e-3 if choices[-1] else 1.0e-3)
    assert sum(choices) == 3, "threads timed once every EXPLORE_EVERY calls, else one thread"
    for _ in range(30):  # the cores free up and the threads now pay off
        payoff.record(True, 0.5e-3)
    assert payoff.parallel() is True


def test_one_parallel_launch_at_a_time() -> None:
    import numba

    with parallel_slot(1) as granted:
        assert granted == 1
    with parallel_slot(2) as granted:
        assert granted == 2
        assert numba.get_num_threads() == min(2, numba.config.NUMBA_NUM_THREADS)
        other: list[int] = []

        def launch() -> None:
            with parallel_slot(2) as g:
                other.append(g)

        thread = threading.Thread(target=launch)
        thread.start()
        thread.join()
        assert other == [1], "a second thread's call meanwhile runs the serial kernels"
    with parallel_slot(2) as granted:
        assert granted == 2, "the slot is free again"


@pytest.fixture(scope="module")
def world_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_test_world(tmp_path_factory.mktemp("threads-world") / "world")


def _episode(world_dir: Path, threads: int, steps: int = 25) -> list[bytes]:
    env = gymnasium.make(
        "drivesim/Overtake-v0", world=str(world_dir), meshes=None, mode="eval",
        config={**SMALL_VIEW, "render_threads": threads},
    )  # fmt: skip
    obs, _ = env.reset(seed=5)
    seen = [obs.tobytes()]
    for step in range(steps):
        obs, *_ = env.step(np.array([0.4 * np.sin(step / 3.0)], np.float32))
        seen.append(obs.tobytes())
    return seen


def test_the_same_pixels_on_one_thread_two_threads_and_a_busy_machine(
    world_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = {"warp": 0, "fill": 0, "raster": 0}
    for name, module, attr in (
        ("warp", warp_kernel, "warp_bands"),
        ("fill", fill_kernel, "pull_push_fill_bands_"),
        ("raster", raster_kernel, "draw_untextured_into_bands"),
    ):
        kernel = getattr(module, attr)

        def counted(*args, _kernel=kernel, _name=name):  # noqa: ANN002, ANN202
            calls[_name] += 1
            return _kernel(*args)

        monkeypatch.setattr(module, attr, counted)
    one = _episode(world_dir, 1)
    assert sum(calls.values()) == 0
    with exact_threads():
        two = _episode(world_dir, 2)
    assert calls["warp"] > 0 and calls["raster"] > 0, f"the parallel kernels ran: {calls}"
    assert one == two, "two threads draw the same observations as one"
    busy = FakeMachine(others_cores=1.0)
    monkeypatch.setattr(cpu_threads, "_FREE", busy.cores())
    _granted(busy, cpu_threads._FREE)
    before = dict(calls)
    assert _episode(world_dir, 2) == one
    assert calls == before, "with no core free, render_threads=2 runs the serial kernels"

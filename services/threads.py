"""How many torch threads each process gets: processes × threads never exceeds the usable CPUs.

Why: OpenMP threads of two torch processes that together ask for more threads than there are cores
spin against each other. Measured on the 2-core dev machine: a small-preset pretraining step takes
0.7–0.9 s alone on 2 threads, and 5.5–7.5 s when a second 2-thread torch process runs beside it.

`plan_threads(processes=N)` gives the plan for N processes that run at the same time: at most one
process per usable CPU (`os.sched_getaffinity`, so a container's or taskset's limit counts), and the
CPUs shared out evenly among them. Work that runs one process at a time gets every CPU. Where the
caller insists on more processes than CPUs (an explicit `train --workers N`), `oversubscribed` is
True and `describe()` says so.
"""

from __future__ import annotations

import os
from dataclasses import dataclass


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class ThreadPlan:
    """`processes` processes at once, each with `threads` torch threads, on `cpus` usable CPUs."""

    cpus: int
    processes: int
    threads: int

    @property
    def oversubscribed(self) -> bool:
        return self.processes * self.threads > self.cpus

    def describe(self, *, independent: bool = False) -> str:
        """One line for the run's log. independent: the processes never wait on each other (benchmark seeds),
        so one thread each over more processes than CPUs only takes turns; DDP workers would spin in their
        collectives instead."""
        text = (f"{self.processes} process(es) × {self.threads} torch thread(s) on {self.cpus} usable CPU(s)")
        if self.oversubscribed and self.threads == 1 and independent:
            text += f" — more processes than CPUs, time-sliced: each step ~{self.processes / self.cpus:.1f}× slower"
        elif self.oversubscribed:
            text += " — OVERSUBSCRIBED: more threads than CPUs, expect steps several times slower"
        return text


def plan_threads(*, processes: int, cpus: int | None = None, cap_processes: bool = True) -> ThreadPlan:
    """The plan for `processes` concurrent processes on `cpus` CPUs (default: usable_cpus()).

    cap_processes=True (benchmark seeds, render workers): run at most `cpus` processes at once, the
    rest waiting. False (an explicit worker count): keep `processes`, one thread each if they exceed
    the CPUs (then the plan is oversubscribed and says so).
    """
    if processes < 1:
        raise ValueError(f"processes must be >= 1, got {processes}")
    cpus = usable_cpus() if cpus is None else cpus
    if cpus < 1:
        raise ValueError(f"cpus must be >= 1, got {cpus}")
    running = min(processes, cpus) if cap_processes else processes
    return ThreadPlan(cpus=cpus, processes=running, threads=max(1, cpus // running))

"""The thread plan: processes × threads never exceeds the usable CPUs (unless a caller insists on more
processes than CPUs, and then the plan says it is oversubscribed)."""

import pytest

from services.threads import ThreadPlan, plan_threads, usable_cpus


@pytest.mark.parametrize("cpus, processes, want", [
    (1, 1, (1, 1)), (1, 3, (1, 1)),                          # one CPU: one process at a time
    (2, 1, (1, 2)), (2, 2, (2, 1)), (2, 3, (2, 1)),          # the dev machine: 3 seeds run 2 at a time
    (8, 1, (1, 8)), (8, 3, (3, 2)), (8, 4, (4, 2)), (8, 8, (8, 1)), (8, 20, (8, 1)),
])
def test_plan_fits_the_cpus(cpus, processes, want):
    plan = plan_threads(processes=processes, cpus=cpus)
    assert (plan.processes, plan.threads) == want
    assert plan.processes * plan.threads <= cpus and not plan.oversubscribed
    assert f"on {cpus} usable CPU(s)" in plan.describe()


def test_an_explicit_worker_count_above_the_cpus_is_flagged():
    plan = plan_threads(processes=4, cpus=2, cap_processes=False)
    assert (plan.processes, plan.threads) == (4, 1) and plan.oversubscribed
    assert "OVERSUBSCRIBED" in plan.describe()
    assert not plan_threads(processes=2, cpus=8, cap_processes=False).oversubscribed


def test_independent_one_thread_processes_above_the_cpus_are_time_sliced_not_spinning():
    """Benchmark seeds never wait on each other: 3 one-thread processes on 2 CPUs take turns (each ~1.5×
    slower); the same plan for DDP workers keeps the OVERSUBSCRIBED warning."""
    plan = plan_threads(processes=3, cpus=2, cap_processes=False)
    assert (plan.processes, plan.threads) == (3, 1) and plan.oversubscribed
    assert "time-sliced: each step ~1.5× slower" in plan.describe(independent=True)
    assert "OVERSUBSCRIBED" in plan.describe()
    assert "OVERSUBSCRIBED" in ThreadPlan(cpus=2, processes=3, threads=2).describe(independent=True)


def test_default_cpus_come_from_the_affinity_mask():
    import os

    assert usable_cpus() == len(os.sched_getaffinity(0))
    assert plan_threads(processes=1).threads == usable_cpus()
    with pytest.raises(ValueError):
        plan_threads(processes=0)

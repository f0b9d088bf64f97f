"""Frontier planner rules, one at a time."""

from companion.core.frontiers import FrontierKey
from companion.core.planner import FrontierPlanner, PlannerParams


def test_a_frontier_found_out_of_reach_step_after_step_counts_one_try_per_cooldown():
    """At a keyframe's origin a goal dropped as blocked is still cooling down, so it is found out
    of reach at every step until then: that is one failed try, not one per step (two would set it
    aside before it was ever tried again)."""
    planner = FrontierPlanner(PlannerParams(max_attempts=2, blocked_cooldown_s=5.0))
    key = FrontierKey(7, 3)
    for k in range(30):
        planner._failed(key, 100.0 + 0.1 * k)
    assert planner.attempts[key] == 1 and key not in planner.set_aside
    planner._failed(key, 105.5)  # tried again after the cooldown, and out of reach again
    assert planner.attempts[key] == 2 and key in planner.set_aside

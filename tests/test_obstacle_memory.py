"""The lead's obstacle memory: remembered returns kept in line with the newest scan."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.core.geometry import Pose2
from companion.core.messages import DepthScan
from companion.core.obstacle_memory import MemoryAlignParams, RecentReturns, scan_walls
from sitl.depth_sensor import cast_rays

BEARINGS = np.linspace(-math.pi / 4, math.pi / 4, 64)
ROOM = np.array(
    [
        [[0.0, 0.0], [6.0, 0.0]],
        [[6.0, 0.0], [6.0, 4.0]],
        [[6.0, 4.0], [0.0, 4.0]],
        [[0.0, 4.0], [0.0, 0.0]],
    ]
)
CORRIDOR = np.array([[[-20.0, 0.0], [20.0, 0.0]], [[-20.0, 1.2], [20.0, 1.2]]])


def scan_from(true_pose: Pose2, walls: np.ndarray, stamp_s: float) -> DepthScan:
    ranges = cast_rays(np.array([true_pose.x_m, true_pose.y_m]), true_pose.yaw_rad + BEARINGS, walls, 5.0)
    return DepthScan(stamp_s, BEARINGS, ranges, 5.0)


def body_points(scan: DepthScan) -> np.ndarray:
    ok = np.isfinite(scan.ranges_m)
    r, b = scan.ranges_m[ok], scan.bearings_rad[ok]
    return np.column_stack((r * np.cos(b), r * np.sin(b)))


def memory_after_drift(walls: np.ndarray, start: Pose2, true_now: Pose2, estimate_now: Pose2, travel_m: float, jamb):
    """A memory of one scan at ``start`` (odometry = truth there) and a jamb beside the vehicle,
    aligned to a scan taken at ``true_now`` that odometry places at ``estimate_now``. Returns the
    jamb where the memory has it and where it truly lies relative to the estimate."""
    memory = RecentReturns(60.0, 1.5, align=MemoryAlignParams())
    first = scan_from(start, walls, 0.0)
    memory.add(0.0, 0.0, np.vstack((start.apply(body_points(first)), [jamb])))
    now = scan_from(true_now, walls, 0.1)
    memory.align(now, estimate_now, travel_m, 0.02)
    remembered = memory.points_xy()[-1]
    truly = estimate_now.apply(true_now.inverse().apply(np.array([jamb])))[0]
    return remembered, truly


def test_scan_walls_join_neighbouring_returns_but_not_across_an_occlusion():
    ranges = np.full(64, 3.0)
    ranges[32:] = 4.5  # a jump of 1.5 m: one surface hides the other
    ranges[10] = np.inf  # no return: no wall through it
    walls = scan_walls(DepthScan(0.0, BEARINGS, ranges, 5.0), 0.02, 0.3)
    assert np.flatnonzero(~walls.ok).tolist() == [9, 10, 31]
    lengths = np.hypot(*(walls.ends_xy - walls.starts_xy)[walls.ok].T)
    assert lengths.max() < 0.3
    # Wall j runs from ray j's return to ray j + 1's, in the sensor's frame.
    assert np.allclose(walls.starts_xy[0], (3.0 * math.cos(BEARINGS[0]), 3.0 * math.sin(BEARINGS[0])))
    assert np.allclose(walls.ends_xy[40], (4.5 * math.cos(BEARINGS[41]), 4.5 * math.sin(BEARINGS[41])))


def test_a_remembered_jamb_out_of_view_is_moved_by_the_drift_the_walls_in_view_show():
    start, true_now = Pose2(2.0, 2.0, 0.0), Pose2(2.3, 2.0, 0.1)
    # Odometry drifted 8 cm and 0.02 rad: about its sigma over a metre's travel (the prior the
    # match weighs the walls against; see MemoryAlignParams).
    estimate_now = Pose2(2.36, 1.95, 0.12)
    jamb = (2.2, 2.7)  # beside the vehicle: out of the new view
    remembered, truly = memory_after_drift(ROOM, start, true_now, estimate_now, 1.0, jamb)
    assert float(np.hypot(*(np.array(jamb) - truly))) > 0.05  # unaligned, it would be this far off
    assert float(np.hypot(*(remembered - truly))) < 0.01


def test_along_a_corridor_the_memory_moves_only_across_it():
    start, true_now = Pose2(0.0, 0.6, 0.0), Pose2(0.3, 0.6, 0.0)
    estimate_now = Pose2(0.4, 0.64, 0.0)  # 10 cm along, 4 cm across
    jamb = (0.1, 1.1)
    remembered, truly = memory_after_drift(CORRIDOR, start, true_now, estimate_now, 0.3, jamb)
    assert abs(remembered[1] - truly[1]) < 0.01  # the walls fix it across
    assert abs(remembered[0] - jamb[0]) < 0.01  # and nothing along: it stays where odometry put it


def test_hovering_a_scan_a_little_off_hardly_moves_the_memory():
    start = Pose2(2.0, 2.0, 0.0)
    # No travel since the memory's scan: the 3 cm the new scan lies off are its own error.
    remembered, _ = memory_after_drift(ROOM, start, start, Pose2(2.03, 2.0, 0.0), 0.0, (2.2, 2.7))
    assert float(np.hypot(*(remembered - (2.2, 2.7)))) < 0.006


def test_memory_not_told_to_align_stays_as_odometry_put_it():
    memory = RecentReturns(60.0, 1.5)  # the perfect-pose baseline's: nothing drifts
    start = Pose2(2.0, 2.0, 0.0)
    memory.add(0.0, 0.0, start.apply(body_points(scan_from(start, ROOM, 0.0))))
    before = memory.points_xy().copy()
    assert memory.align(scan_from(Pose2(2.3, 2.0, 0.1), ROOM, 0.1), Pose2(2.36, 1.95, 0.12), 0.3, 0.02) is None
    assert np.array_equal(memory.points_xy(), before)


def test_what_the_walls_do_not_fix_adds_to_how_far_off_the_memory_may_lie():
    """Each alignment adds what it leaves unknown to the memory's sigma: in a room (walls
    every way) a few millimetres; along a corridor the odometry's drift along it, as if
    unaligned; a scan of open space (nothing to align to) the drift in full."""
    prior_m = 0.002 + 0.1 * math.sqrt(1.0)  # MemoryAlignParams over 1 m of travel

    def sigma_after(walls: np.ndarray, start: Pose2, now: Pose2, walls_now: np.ndarray | None = None) -> float:
        memory = RecentReturns(60.0, 1.5, align=MemoryAlignParams())
        memory.add(0.0, 0.0, start.apply(body_points(scan_from(start, walls, 0.0))))
        assert memory.sigmas_m().max() == 0.0  # just seen
        memory.align(scan_from(now, walls if walls_now is None else walls_now, 0.1), now, 1.0, 0.02)
        sigmas = memory.sigmas_m()
        assert np.all(sigmas == sigmas[0])  # one scan: one sigma
        return float(sigmas[0])

    assert sigma_after(ROOM, Pose2(2.0, 2.0, 0.0), Pose2(2.3, 2.0, 0.1)) < 0.2 * prior_m
    along = sigma_after(CORRIDOR, Pose2(0.0, 0.6, 0.0), Pose2(0.3, 0.6, 0.0))
    assert 0.9 * prior_m < along < 1.2 * prior_m
    open_space = np.zeros((0, 2, 2))
    assert sigma_after(ROOM, Pose2(2.0, 2.0, 0.0), Pose2(2.3, 2.0, 0.1), open_space) > prior_m


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.booleans(), st.integers(0, 6), st.floats(-0.5, 1.0), st.floats(0.0, 0.8), st.integers(0, 2**16))
    )
)
def test_the_memory_keeps_each_scan_by_its_age_travel_and_what_was_forgotten(ops):
    """The memory's bookkeeping against a plain list of scans: a scan leaves after ``memory_s``
    seconds or ``memory_m`` metres, or when the clock goes back past it; forgetting points drops a
    scan left with none, never the newest; each point's sigma is its own scan's."""
    memory = RecentReturns(1.0, 1.5, align=MemoryAlignParams())
    model: list[tuple[float, float, np.ndarray]] = []  # stamp, travel, points
    stamp, travel, label = 0.0, 0.0, 0.0
    for forget, count, dt_s, dm, bits in ops:
        if forget and model:
            points = np.vstack([m[2] for m in model])
            mask = np.array([(bits >> (i % 16)) & 1 == 1 for i in range(points.shape[0])], dtype=bool)
            memory.keep(mask)
            start, kept = 0, []
            for i, (s, t, p) in enumerate(model):
                left = p[mask[start : start + p.shape[0]]]
                start += p.shape[0]
                if left.shape[0] or i == len(model) - 1:
                    kept.append((s, t, left))
            model = kept
            continue
        stamp, travel = stamp + dt_s, travel + dm
        points = label + np.arange(2 * count, dtype=np.float64).reshape(-1, 2) / 100.0
        label += 1.0
        memory.add(stamp, travel, points)
        model = [m for m in model if m[0] <= stamp]
        model.append((stamp, travel, points))
        model = [m for m in model if m[0] >= stamp - 1.0 - 1e-9 and m[1] >= travel - 1.5]
    expected = np.vstack([m[2] for m in model]) if model else np.zeros((0, 2))
    assert np.array_equal(memory.points_xy(), expected)
    assert memory.newest_count() == (model[-1][2].shape[0] if model else 0)
    if model:
        # After one alignment with nothing to align to, each scan's sigma grows by the same
        # amount: every point still carries one (its scan's), the newest's included.
        memory.align(
            DepthScan(stamp + 0.1, BEARINGS, np.full(BEARINGS.size, np.inf), 5.0), Pose2(50.0, 50.0, 0.0), travel, 0.02
        )
        sigmas = memory.sigmas_m()
        assert sigmas.shape == (expected.shape[0],) and np.all(sigmas > 0.0)

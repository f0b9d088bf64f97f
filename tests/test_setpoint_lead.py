"""The setpoint lead: the companion's speed limit, and its stop short of seen obstacles."""

import dataclasses
import math

import numpy as np
import pytest

from companion.core.geometry import Pose2, first_contact
from companion.core.messages import Setpoint
from companion.core.setpoint_lead import LeadParams, limit_lead, limit_lead_facing_memory, stop_path

BODY_M = 0.25
PARAMS = LeadParams(max_lead_m=1.5, contact_margin_m=0.05, stop_margin_m=0.1, speed_margin_s=0.0)  # touching at 0.3 m
NO_RETURNS = np.zeros((0, 2))


def wall(x_m: float) -> np.ndarray:
    """Returns along a wall across the way at x = ``x_m``."""
    return np.column_stack((np.full(41, x_m), np.linspace(-2.0, 2.0, 41)))


def lead_of(sp: Setpoint, pose: Pose2) -> float:
    return math.hypot(sp.x_m - pose.x_m, sp.y_m - pose.y_m)


def test_a_far_setpoint_is_brought_within_the_maximum_lead_on_its_line():
    pose = Pose2(1.0, 1.0, 0.0)
    sp = limit_lead(Setpoint(5.0, 4.0, 0.7), pose, (0.0, 0.0), NO_RETURNS, BODY_M, PARAMS)
    assert lead_of(sp, pose) == pytest.approx(1.5)
    assert math.atan2(sp.y_m - 1.0, sp.x_m - 1.0) == pytest.approx(math.atan2(3.0, 4.0))
    assert sp.yaw_rad == 0.7
    near = Setpoint(1.5, 1.2, 0.0)
    assert limit_lead(near, pose, (0.0, 0.0), NO_RETURNS, BODY_M, PARAMS) == near


def test_towards_a_wall_the_setpoint_stops_short_of_touching_it():
    pose = Pose2(0.0, 0.0, 0.0)
    sp = limit_lead(Setpoint(3.0, 0.0, 0.0), pose, (0.0, 0.0), wall(1.0), BODY_M, PARAMS)
    assert sp.x_m == pytest.approx(1.0 - 0.3 - 0.1)
    # Within the wall's standoff already: hold, never closer.
    sp = limit_lead(Setpoint(3.0, 0.0, 0.0), Pose2(0.65, 0.0, 0.0), (0.0, 0.0), wall(1.0), BODY_M, PARAMS)
    assert sp.x_m == pytest.approx(0.65)


def clearance_m(path: np.ndarray, points: np.ndarray) -> float:
    """How close the way ``path`` comes to any of ``points``."""
    return float(np.min(np.hypot(*(path[:, None, :] - points[None, :, :]).transpose(2, 0, 1))))


def test_the_way_predicted_for_a_setpoint_held_still_comes_to_rest_on_it():
    """From rest it flies to the setpoint and stops there; moving, with the setpoint where the
    vehicle is, it coasts the delay, brakes at the modelled acceleration and comes back."""
    path = stop_path((0.0, 0.0), (1.0, 0.5), PARAMS)
    assert np.allclose(path[0], 0.0) and np.allclose(path[-1], [1.0, 0.5], atol=0.02)
    along = path @ np.array([1.0, 0.5]) / math.hypot(1.0, 0.5)
    assert along.max() < math.hypot(1.0, 0.5) + 0.05  # no more overshoot than a step's discretisation
    path = stop_path((1.2, 0.0), (0.0, 0.0), PARAMS)
    travel = 1.2 * PARAMS.model_delay_s + 1.2**2 / (2.0 * PARAMS.model_accel_mps2)
    assert path[:, 0].max() == pytest.approx(travel, abs=1.2 * PARAMS.model_step_s)
    assert np.allclose(path[-1], 0.0, atol=0.05) and np.allclose(path[:, 1], 0.0)


def test_moving_fast_at_a_wall_it_brakes_whatever_the_setpoint():
    """Momentum carries the vehicle on while it turns: at 1.2 m/s towards a wall 1 m ahead it
    cannot turn away in time, so a setpoint off to the side gets no lead (it brakes); slower, it
    gets the lead whose predicted way keeps clear of the wall."""
    pose = Pose2(0.0, 0.0, 0.0)
    sideways = Setpoint(0.0, 3.0, 0.0)
    assert lead_of(limit_lead(sideways, pose, (0.0, 0.0), wall(1.0), BODY_M, PARAMS), pose) == pytest.approx(1.5)
    assert lead_of(limit_lead(sideways, pose, (1.2, 0.0), wall(1.0), BODY_M, PARAMS), pose) == pytest.approx(0.0)
    assert lead_of(limit_lead(sideways, pose, (0.8, 0.0), wall(1.0), BODY_M, PARAMS), pose) == pytest.approx(1.5)
    slower = limit_lead(sideways, pose, (1.0, 0.0), wall(1.0), BODY_M, PARAMS)
    assert 0.0 < lead_of(slower, pose) < 1.5
    assert clearance_m(stop_path((1.0, 0.0), (slower.x_m, slower.y_m), PARAMS), wall(1.0)) >= 0.3
    assert clearance_m(stop_path((1.0, 0.0), (0.0, 1.5), PARAMS), wall(1.0)) < 0.3  # the full lead's way


def test_without_the_predicted_way_the_motions_straight_line_limits_the_lead():
    """The tuning without a back end: moving at a wall, a setpoint off to the side is cut to the
    free travel along the motion less the stop margin, not to braking."""
    pose = Pose2(0.0, 0.0, 0.0)
    line = dataclasses.replace(PARAMS, predict_way=False)
    sideways = Setpoint(0.0, 3.0, 0.0)
    assert lead_of(limit_lead(sideways, pose, (1.2, 0.0), wall(1.0), BODY_M, line), pose) == pytest.approx(0.6)
    assert lead_of(limit_lead(sideways, pose, (0.05, 0.0), wall(1.0), BODY_M, line), pose) == pytest.approx(1.5)


def test_down_a_narrow_corridor_a_little_sideways_motion_does_not_hold_the_vehicle():
    """The corridor crawl: 0.1 m off the middle of a 1 m corridor, moving at 1 m/s with its
    velocity 5 degrees towards the nearer wall, the vehicle only has to stop that sideways drift
    (a few centimetres), not its whole motion: the setpoint keeps half its lead at least (1 m/s
    and more). Checking the motion's straight line instead held it (the lead cut to centimetres)."""
    pose = Pose2(0.0, -0.1, 0.0)
    x = np.linspace(-3.0, 6.0, 91)
    walls = np.vstack((np.column_stack((x, np.full(91, 0.5))), np.column_stack((x, np.full(91, -0.5)))))
    velocity = (math.cos(math.radians(5.0)), -math.sin(math.radians(5.0)))
    ahead = Setpoint(5.0, 0.0, 0.0)
    params = LeadParams(memory_margin_m=0.05, speed_margin_s=0.15)
    sp = limit_lead(ahead, pose, velocity, NO_RETURNS, BODY_M, params, remembered_xy=walls)
    assert lead_of(sp, pose) >= 0.75
    # Its motion's straight line meets the nearer wall's berth within 0.3 m: checked along it, the
    # lead would have been cut to that less the stop margin.
    contact = 0.95 * 0.4
    assert first_contact(walls - [pose.x_m, pose.y_m], velocity, contact)[0] < 0.3
    # Turned 30 degrees at the wall it must brake short of it.
    steep = (math.cos(math.radians(30.0)), -math.sin(math.radians(30.0)))
    assert lead_of(limit_lead(ahead, pose, steep, NO_RETURNS, BODY_M, params, walls), pose) < 0.5


def test_beside_a_wall_closer_than_the_contact_radius_it_may_still_move_along_it():
    pose = Pose2(0.0, 0.0, 0.0)
    beside = np.column_stack((np.linspace(-1.0, 3.0, 41), np.full(41, 0.28)))  # 0.28 m to the left
    along = limit_lead(Setpoint(3.0, 0.0, 0.0), pose, (0.0, 0.0), beside, BODY_M, PARAMS)
    assert lead_of(along, pose) == pytest.approx(1.5)
    towards = limit_lead(Setpoint(0.0, 3.0, 0.0), pose, (0.0, 0.0), beside, BODY_M, PARAMS)
    assert lead_of(towards, pose) == pytest.approx(0.0)


def test_inside_the_berth_and_drifting_in_a_way_no_deeper_than_braking_keeps_its_lead():
    """0.28 m from a wall and moving 0.5 m/s at 20 degrees towards it, even braking carries the
    vehicle 4 cm deeper into the berth (the coast, then the stop). A setpoint away from the wall,
    or along and away, comes no deeper and keeps its full lead: braking instead left the vehicle
    hovering beside walls (a no-SLAM room ran short). Along the wall, deeper, it is cut."""
    pose = Pose2(0.0, 0.0, 0.0)
    beside = np.column_stack((np.linspace(-1.0, 3.0, 81), np.full(81, 0.28)))
    velocity = (0.5 * math.cos(math.radians(20.0)), 0.5 * math.sin(math.radians(20.0)))
    braking = stop_path(velocity, (0.0, 0.0), PARAMS)
    assert clearance_m(braking, beside) < 0.95 * 0.28 - 0.03
    for away in (Setpoint(0.0, -3.0, 0.0), Setpoint(3.0, -0.5, 0.0)):
        sp = limit_lead(away, pose, velocity, beside, BODY_M, PARAMS)
        assert lead_of(sp, pose) == pytest.approx(1.5)
        way = stop_path(velocity, (sp.x_m, sp.y_m), PARAMS)
        assert clearance_m(way, beside) >= clearance_m(braking, beside) - 0.005
    along = limit_lead(Setpoint(3.0, 0.0, 0.0), pose, velocity, beside, BODY_M, PARAMS)
    assert 0.0 < lead_of(along, pose) < 1.5


def test_at_speed_a_line_passing_close_by_a_corner_counts_as_blocked():
    """The office-3 crash: flying at 1.5 m/s on a line passing 0.31 m from a door jamb's corner
    (just outside the 0.3 m contact radius), a small turn put the corner in the way when the
    vehicle could no longer brake. The contact radius grows with speed, so that line is cut at
    speed, and still free when hovering; at 1.5 m/s the vehicle can no longer stop short of the
    corner at all, so it brakes."""
    params = LeadParams(max_lead_m=1.5, contact_margin_m=0.05, stop_margin_m=0.1, speed_margin_s=0.15)
    pose = Pose2(0.0, 0.0, 0.0)
    corner = np.array([[1.2, -0.31]])
    ahead = Setpoint(3.0, 0.0, 0.0)
    hovering = limit_lead(ahead, pose, (0.0, 0.0), corner, BODY_M, params)
    assert lead_of(hovering, pose) == pytest.approx(1.5)
    slow = limit_lead(ahead, pose, (0.5, 0.0), corner, BODY_M, params)
    reach = 0.3 + 0.15 * 0.5
    assert lead_of(slow, pose) == pytest.approx(1.2 - math.sqrt(reach**2 - 0.31**2) - 0.1)
    assert lead_of(limit_lead(ahead, pose, (1.5, 0.0), corner, BODY_M, params), pose) == pytest.approx(0.0)


def test_a_remembered_return_is_given_a_wider_berth_than_one_in_view():
    """A return out of view now was sampled at the ray spacing and has drifted with odometry
    since: the line must pass it by the memory margin more (a jamb's corner beside the vehicle,
    between two remembered samples, was touched at the plain margin)."""
    params = LeadParams(
        max_lead_m=1.5, contact_margin_m=0.05, stop_margin_m=0.1, speed_margin_s=0.0, memory_margin_m=0.05
    )
    pose, sp = Pose2(0.0, 0.0, 0.0), Setpoint(3.0, 0.0, 0.0)
    beside = np.array([[1.0, 0.33]])  # the line passes 0.33 m off: clear of 0.30, not of 0.35
    assert lead_of(limit_lead(sp, pose, (0.0, 0.0), beside, BODY_M, params), pose) == pytest.approx(1.5)
    held = limit_lead(sp, pose, (0.0, 0.0), NO_RETURNS, BODY_M, params, remembered_xy=beside)
    assert lead_of(held, pose) < 1.0 - 0.1  # short of the point, by the stop margin at least


def test_a_remembered_return_that_may_have_drifted_is_given_a_berth_wider_by_its_sigmas():
    """How far off each remembered return may lie by now (its sigma: the drift no alignment took
    out) widens its berth by ``memory_sigmas`` of it: the line passing 0.43 m off a return is
    clear of its plain 0.35 m, not of 0.35 + 2 x 0.05 m; one return's doubt holds no other."""
    params = LeadParams(
        max_lead_m=1.5,
        contact_margin_m=0.05,
        stop_margin_m=0.1,
        speed_margin_s=0.0,
        memory_margin_m=0.05,
        memory_sigmas=2.0,
    )
    pose, sp = Pose2(0.0, 0.0, 0.0), Setpoint(3.0, 0.0, 0.0)
    beside = np.array([[1.0, 0.43], [0.6, -0.43]])

    def lead_m(sigmas: list[float]) -> float:
        return lead_of(limit_lead(sp, pose, (0.0, 0.0), NO_RETURNS, BODY_M, params, beside, np.array(sigmas)), pose)

    assert lead_m([0.0, 0.0]) == pytest.approx(1.5)
    assert lead_m([0.035, 0.0]) == pytest.approx(1.5)  # 0.43 m off: clear of 0.35 + 0.07 m
    assert lead_m([0.05, 0.0]) < 1.0 - 0.1  # held short of the far one, by the stop margin
    assert lead_m([0.0, 0.05]) < 0.6 - 0.1  # or of the near one


def test_held_by_a_remembered_return_alone_the_vehicle_is_told_to_look_at_it():
    """A return out of view, 0.33 m off the line just ahead, holds the vehicle (the memory's
    wider berth), where the newest scan alone would let it go: that return is the one to look
    at, so the sensor decides. In view, or with a newest return holding it too, there is nothing
    to look at: the scan already decides."""
    params = LeadParams(
        max_lead_m=1.5, contact_margin_m=0.05, stop_margin_m=0.1, speed_margin_s=0.0, memory_margin_m=0.05
    )
    pose, sp = Pose2(0.0, 0.0, 0.0), Setpoint(3.0, 0.0, 0.0)
    beside = np.array([[0.2, 0.33], [0.0, -1.0], [1.0, 0.9]])
    held = limit_lead(sp, pose, (0.0, 0.0), NO_RETURNS, BODY_M, params, remembered_xy=beside)
    assert lead_of(held, pose) == pytest.approx(0.0)
    facing, blocker = limit_lead_facing_memory(sp, pose, (0.0, 0.0), NO_RETURNS, BODY_M, params, beside)
    assert blocker is not None and np.allclose(blocker, [0.2, 0.33])
    assert (facing.x_m, facing.y_m) == (held.x_m, held.y_m)
    assert facing.yaw_rad == pytest.approx(math.atan2(0.33, 0.2))  # turned to face it

    def blocker_of(setpoint: Setpoint, returns: np.ndarray, remembered: np.ndarray) -> np.ndarray | None:
        limited, blocker = limit_lead_facing_memory(setpoint, pose, (0.0, 0.0), returns, BODY_M, params, remembered)
        assert blocker is not None or limited.yaw_rad == setpoint.yaw_rad  # the yaw kept
        return blocker

    assert blocker_of(sp, beside, NO_RETURNS) is None
    assert blocker_of(sp, wall(0.35), beside) is None
    # Away from it the memory does not hold the vehicle: nothing to look at.
    assert blocker_of(Setpoint(-3.0, 0.0, 0.0), NO_RETURNS, beside) is None

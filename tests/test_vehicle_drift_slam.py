import math
from pathlib import Path

import numpy as np

from companion.core.geometry import Pose2
from sitl.drift import DriftParams, OdometryDrift
from sitl.slam import SimulatedSlam, SlamParams
from sitl.vehicle import Vehicle, VehicleParams


def flat_vehicle(noise: float = 0.0, seed: int = 0) -> Vehicle:
    drift = OdometryDrift(DriftParams(scale=noise), Pose2(), np.random.default_rng(seed))
    return Vehicle(VehicleParams(), Pose2(), drift)


def test_vehicle_respects_speed_acceleration_and_yaw_rate_limits():
    v = flat_vehicle()
    dt = 0.02
    speeds, yaws = [], []
    prev_v = np.zeros(2)
    for _ in range(1000):
        v.step(dt, Pose2(50.0, 0.0, math.pi))
        speeds.append(float(np.hypot(*v.velocity)))
        assert np.hypot(*(v.velocity - prev_v)) <= 1.0 * dt + 1e-9
        prev_v = v.velocity.copy()
        yaws.append(v.true_pose.yaw_rad)
    assert max(speeds) <= 1.5 + 1e-9 and max(speeds) > 1.45
    rates = np.abs(np.diff(np.unwrap(yaws))) / dt
    assert rates.max() <= math.radians(90) + 1e-6


def test_vehicle_settles_on_its_setpoint():
    v = flat_vehicle()
    for _ in range(1500):
        v.step(0.02, Pose2(3.0, -2.0, 1.0))
    assert v.true_pose.distance_to(Pose2(3.0, -2.0)) < 0.02
    assert abs(v.true_pose.yaw_rad - 1.0) < 0.01


def test_drift_statistics_match_the_configured_sigma():
    rng = np.random.default_rng(42)
    errors = []
    for _ in range(2000):
        d = OdometryDrift(DriftParams(), Pose2(), rng)
        d.integrate(Pose2(1.0, 0.0, 0.0))
        errors.append((d.estimate.x_m - 1.0, d.estimate.y_m, d.estimate.yaw_rad))
    e = np.array(errors)
    assert np.allclose(e[:, :2].std(axis=0), 0.1, rtol=0.1)
    assert math.isclose(e[:, 2].std(), 0.015, rel_tol=0.1)
    zero = OdometryDrift(DriftParams(scale=0.0), Pose2(), rng)
    zero.integrate(Pose2(1.0, 0.0, 0.0))
    assert zero.estimate == Pose2(1.0, 0.0, 0.0)


def _travel(slam: SimulatedSlam, points, t0=0.0):
    out = []
    for i, (x, y) in enumerate(points):
        c = slam.observe(t0 + i * 0.5, Pose2(x, y, 0.0))
        if c is not None:
            out.append(c)
    return out


def test_loop_closure_fires_on_return_with_line_of_sight_and_reports_the_true_transform():
    slam = SimulatedSlam(SlamParams(), np.zeros((0, 2, 2)))
    path = (
        [(float(x), 0.0) for x in range(0, 8)]
        + [(7.0, float(y)) for y in range(1, 4)]
        + [(float(x), 3.0) for x in range(6, -1, -1)]
    )
    closures = _travel(slam, path)
    assert closures
    c = closures[0]
    assert c.earlier_stamp_s < c.current_stamp_s
    assert math.hypot(c.earlier_to_current.x_m, c.earlier_to_current.y_m) <= 4.0


def test_no_loop_closure_through_a_wall():
    wall = np.array([[[-10.0, 1.5], [20.0, 1.5]]])
    slam = SimulatedSlam(SlamParams(), wall)
    path = (
        [(float(x), 0.0) for x in range(0, 8)]
        + [(7.0, float(y)) for y in range(1, 4)]
        + [(float(x), 3.0) for x in range(6, -1, -1)]
    )
    assert _travel(slam, path) == []


def test_the_simulated_estimator_reports_its_velocity_in_its_own_drifting_frame():
    """The reported velocity is the true one turned into the estimate's frame, plus its small
    noise; not the drifting pose's derivative, and none of it without drift."""
    from sitl.simulation import SimParams, Simulation
    from sitl.world import load_world

    world = load_world(Path(__file__).resolve().parents[1] / "config" / "maps" / "hall.geojson")
    s = world.start
    ahead = Pose2(s.x_m + math.cos(s.yaw_rad), s.y_m + math.sin(s.yaw_rad), s.yaw_rad + 0.5)  # 1 m on, turning
    assert world.clearance_at(ahead.x_m, ahead.y_m) > 0.5
    errors, turned = [], []
    for scale in (0.0, 1.0):
        p = SimParams()
        sim = Simulation(world, SimParams(p.sensor, p.vehicle, DriftParams(scale=scale), p.slam), seed=3)
        frame = sim.frame()
        for _ in range(12):
            frame = sim.advance(ahead)
        assert not sim.crashed and float(np.hypot(*sim.vehicle.velocity)) > 0.3
        est, true = frame.odometry.pose, frame.true_pose
        turn = est.yaw_rad - true.yaw_rad
        vx, vy = (float(v) for v in sim.vehicle.velocity)
        expected = (math.cos(turn) * vx - math.sin(turn) * vy, math.sin(turn) * vx + math.cos(turn) * vy)
        assert frame.odometry.velocity_xy is not None
        errors.append(math.dist(frame.odometry.velocity_xy, expected))
        turned.append(abs(turn))
    assert errors[0] == 0.0 and turned[0] == 0.0
    assert 0.0 < errors[1] < 0.25 and turned[1] > 0.0  # a few sigma of 0.05 m/s per axis

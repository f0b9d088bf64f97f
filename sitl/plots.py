"""Figures like the thesis's figure 3.3 and 3.5, written as PNG files (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from companion.core.fov_polygon import VertexKind
from companion.core.pose_graph import EdgeType
from sitl.runner import PolygonPolicy, RunTrace
from sitl.world import World


def _draw_world(ax: plt.Axes, world: World) -> None:
    for seg in world.walls:
        ax.plot(seg[:, 0], seg[:, 1], color="black", linewidth=1.2)
    ax.set_aspect("equal")


def write_plots(world: World, trace: RunTrace, out_dir: Path, baseline: RunTrace | None = None) -> list[Path]:
    """Write the map, trajectory, coverage, pose-graph and coverage-over-time figures."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    policy = trace.policy
    if isinstance(policy, PolygonPolicy):
        written.append(_map_figure(world, trace, policy, out_dir / "map.png"))
        written.append(_pose_graph_figure(policy, out_dir / "pose_graph.png"))
    written.append(_trajectory_figure(world, trace, out_dir / "trajectories.png"))
    written.append(_coverage_figure(world, trace, out_dir / "coverage_grid.png"))
    written.append(_coverage_time_figure(trace, baseline, out_dir / "coverage_over_time.png"))
    return written


def _map_figure(world: World, trace: RunTrace, policy: PolygonPolicy, path: Path) -> Path:
    """Each keyframe's polygon drawn at the true pose it was taken from, with vertex types."""
    fig, ax = plt.subplots(figsize=(9, 7))
    _draw_world(ax, world)
    m = policy.explorer.map
    for k, kf in m.keyframes.items():
        pose = trace.keyframe_true_poses.get(k)
        if pose is None:
            continue
        v = pose.apply(kf.polygon.vertices_xy)
        ring = np.vstack((v, v[:1]))
        ax.fill(ring[:, 0], ring[:, 1], color="tab:green", alpha=0.03)
        ob = kf.kinds == VertexKind.OBSTACLE
        fr = kf.kinds == VertexKind.FRONTIER
        ax.scatter(v[ob, 0], v[ob, 1], s=2, color="tab:red")
        ax.scatter(v[fr, 0], v[fr, 1], s=6, color="tab:blue")
    ax.set_title(f"{world.name}: keyframe polygons at true poses; obstacle (red), open frontier (blue)")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _trajectory_figure(world: World, trace: RunTrace, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(9, 7))
    _draw_world(ax, world)
    t = np.array([[p.x_m, p.y_m] for p in trace.true_path])
    e = np.array([[p.x_m, p.y_m] for p in trace.estimated_path])
    ax.plot(t[:, 0], t[:, 1], color="tab:green", linewidth=1, label="true")
    ax.plot(e[:, 0], e[:, 1], color="tab:orange", linewidth=1, label="estimated (odometry)")
    ax.legend(loc="upper right")
    ax.set_title("true and estimated trajectories")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _coverage_figure(world: World, trace: RunTrace, path: Path) -> Path:
    grid = trace.coverage
    assert grid is not None
    s = grid.spec
    img = np.full((s.rows, s.cols, 3), 1.0)
    img[grid.observable & ~grid.explored] = (0.35, 0.55, 0.9)
    img[grid.observable & grid.explored] = (1.0, 0.65, 0.2)
    fig, ax = plt.subplots(figsize=(9, 7))
    extent = (s.x0_m, s.x0_m + s.cols * s.resolution_m, s.y0_m, s.y0_m + s.rows * s.resolution_m)
    ax.imshow(img, origin="lower", extent=extent, interpolation="nearest")
    _draw_world(ax, world)
    ax.set_title(f"coverage {grid.coverage:.3f}: explored (orange), unexplored (blue)")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _pose_graph_figure(policy: PolygonPolicy, path: Path) -> Path:
    """The pose graph at the keyframes' odometry poses (as the drifting estimate placed them)."""
    m = policy.explorer.map
    fig, ax = plt.subplots(figsize=(9, 7))
    for edge in m.graph.edges:
        a = m.keyframes[edge.from_id].odom_pose
        b = m.keyframes[edge.to_id].odom_pose
        style = ("tab:gray", 0.8) if edge.kind is EdgeType.ODOMETRY else ("tab:green", 1.5)
        ax.plot([a.x_m, b.x_m], [a.y_m, b.y_m], color=style[0], linewidth=style[1])
    xy = np.array([[kf.odom_pose.x_m, kf.odom_pose.y_m] for kf in m.keyframes.values()])
    if len(xy):
        ax.scatter(xy[:, 0], xy[:, 1], s=4, color="black")
    ax.set_aspect("equal")
    ax.set_title(f"pose graph: {len(m)} keyframes, {m.loop_closures} loop closures (green)")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _coverage_time_figure(trace: RunTrace, baseline: RunTrace | None, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for tr, label in ((trace, trace.report["planner"]), (baseline, "grid (perfect poses)")):
        if tr is None:
            continue
        c = np.array(tr.coverage_over_time)
        ax.plot(c[:, 0], c[:, 1], label=label)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("coverage")
    ax.set_ylim(0, 1.02)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path

"""The local-polygon map (thesis 2.8, "second approach").

One field-of-view polygon per keyframe, kept in that keyframe's own frame; keyframes joined by a
pose graph of relative transforms. For a keyframe, the *neighbourhood* is every keyframe reached by
a breadth-first walk along the graph whose polygon, moved into this keyframe's frame, intersects
this keyframe's polygon (eq. 2.13, 2.14): a branch stops where the polygons no longer overlap. The
*grown polygon* is the union of the neighbourhood's polygons. A frontier vertex is closed (typed
free, eq. 2.15) when the space just beyond it lies inside another view of the neighbourhood, or
when another view saw a wall right there. Loop closures add an edge and re-run this closing for the
newer keyframe; no vertex is ever moved.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import shapely
from numpy.typing import NDArray

from companion.core.errors import GraphError
from companion.core.fov_polygon import KIND_FRONTIER, KIND_OBSTACLE, FovPolygon, VertexKind
from companion.core.geometry import FloatArray, Pose2, apply_each, apply_grouped, move_each, point_segment_distances
from companion.core.pose_graph import EdgeType, PoseGraph
from companion.core.slivers import SliverParams, sliver_vertices


@dataclass(frozen=True, slots=True)
class MapParams:
    """Tuning for frontier closing."""

    closing_offset_m: float = 0.15  # how far beyond a frontier vertex another view must reach
    closing_depth_m: float = 0.4  # and how far (or to a wall) it must reach: a sliver does not close
    # A neighbour whose polygon, placed in a keyframe's frame, holds a wall that keyframe itself
    # saw this deep inside its free space, or whose walls lie so deep in the keyframe's, is
    # misplaced (drift along a long chain of the graph): in that keyframe's view it neither
    # closes frontiers nor has its own closed. One placed 1 m off across a door closed the
    # door's frontiers from the corridor, and the room behind was never entered (lshape seed 3
    # with the start turn: `complete` at coverage 0.952).
    misplaced_depth_m: float = 0.3
    misplaced_min_hops: int = 6  # nearer along the graph, drift is too small to place a view so far off
    # A neighbour that far along may also be placed off along its own walls, which no test of
    # disagreement sees: a range-limit vertex with no wall beside it in its own view (a doorway's)
    # lies on such a neighbour's wall only where that wall runs on past it, both ways, by the
    # drift its chain allows (``chain_margin_per_hop_m`` a hop). A neighbour 7 hops on, placed
    # 0.5 m off by a loop closure, put a door's jamb across the doorway's range-limit vertex,
    # and the room behind was never entered (lshape seed 1 in session 53's variant H).
    wall_snap_m: float = 0.15  # a frontier this close to a wall another view saw is closed
    # A vertex at the sensor's range limit (no return on its ray) closes on a neighbour's wall
    # this close: where a wall leaves the range, the last ray's limit lies on it, and neighbours
    # placed 0.3 m off by drift left such vertices open, flown back to after coverage was full
    # (spiral seed 3: 99 keyframes back for one, at 195 s of 347 s). Shadow and field-of-view
    # side vertices keep the tighter snap (a door's lie beyond its jamb), and so do views along
    # the graph (``graph_wall_snap_m``): drift along a chain is larger, and without loop
    # closures the room's run ended at coverage 0.95 when they snapped this far too. Past a
    # wall's end, no farther from that end than ``wall_snap_m`` (a door lies past a jamb),
    # unless the vertex's own view saw a wall by it leave the range (see ``_past_end_m``).
    range_limit_snap_m: float = 0.35
    # The neighbourhood walk goes on through this many views in a row that do not overlap the
    # keyframe: a turn in place leaves views looking away between two that see the same place.
    neighbourhood_bridge_hops: int = 4
    # Views joined by an edge shorter than this (a turn in place) are bridged whatever their
    # number: the start's full turn left ten views at one spot, and the views flown on from
    # there never met its first (east-facing) one, whose frontiers stayed open all run.
    neighbourhood_still_m: float = 0.2
    # The walk asks whether views overlap the keyframe for this many views beyond each level at
    # once (the same walk; a speed setting only, see ``PoseGraph.walk_levels``).
    neighbourhood_ask_ahead: int = 32
    # Closing against views outside the neighbourhood, reached along the pose graph: the vertex
    # must lie deeper inside the other view the longer the chain (drift accumulates along it),
    # at least as deep as the closing depth beyond the offset.
    chain_margin_per_hop_m: float = 0.05
    chain_max_margin_m: float = 1.0
    chain_max_hops: int = 400
    # Whether a view so far along the chain that the margin is capped (past 20 hops at the
    # defaults) closes frontiers at all. Loop closures shorten chains, but a chain of 40 hops
    # with ten of the simulated back end's closures (0.1-0.6 m off each) placed views 2 m off,
    # and they closed a corridor's end as seen: campus seed 1 `complete` at coverage 0.942.
    chain_closes_past_cap: bool = False
    # and a vertex this close to a wall such a view saw is closed too (as ``wall_snap_m`` does
    # within the neighbourhood): a vertex a view left on a wall it saw at a grazing angle, where
    # only views outside the neighbourhood saw that wall closer.
    graph_wall_snap_m: float = 0.15
    # A vertex on an occlusion's shadow edge closes on a wall only on the side that wall was seen
    # from, or at most this far behind its face (see _near_walls). In session 20, 0.1 m cost 0.3 %
    # of the exploration time on seeds 1-5 and 6-10 and 3.6 % on 11-15 (5 cm: 4.6 % on 1-5);
    # both kept apartment's doors open.
    wall_behind_m: float = 0.1
    # Without a SLAM back end (no loop closures), a revisited place never joins the neighbourhood
    # and a new view's frontiers there would send the vehicle round the same room for ever: close
    # each new keyframe's frontiers against every view along the graph too. It can close a real
    # frontier where drift exceeds the margin, so it is off when loop closures arrive.
    close_new_through_graph: bool = False
    # A frontier whose unseen space beyond is only a sliver (between seen space and walls, or
    # behind a gap between two walls' ends) is closed when the planner first weighs it: see
    # slivers.py. ``SliverParams(reach_m=0.0)`` turns it off.
    slivers: SliverParams = field(default_factory=SliverParams)


def _snaps_m(at_range_limit: NDArray[np.bool_], snap_m: float, range_limit_snap_m: float) -> FloatArray:
    """Each vertex's wall snap: ``snap_m``, or at least ``range_limit_snap_m`` at the range limit."""
    return np.where(at_range_limit, max(snap_m, range_limit_snap_m), snap_m)


@dataclass(slots=True)
class Keyframe:
    """A pose-graph vertex: its polygon (immutable) and the current kind of each vertex."""

    keyframe_id: int
    stamp_s: float
    odom_pose: Pose2  # the state estimate when it was taken (current odometry frame; drifts)
    polygon: FovPolygon
    kinds: NDArray[np.int8] = field(init=False)
    radius_m: float = field(init=False)
    walls: FloatArray = field(init=False)  # the polygon's obstacle edges (M, 2, 2), computed once
    wall_runs: FloatArray = field(init=False)  # (M, 2): how far each edge's wall runs on before and after it
    open_edges: FloatArray = field(init=False)  # and its other edges, bordering unseen space
    corners_xy: FloatArray = field(init=False)  # the polygon shape's own coordinates (N, 2)
    # A disc holding the view (centre x, y and radius): round its bounding box's centre, not the
    # sensor, so a field of view's wedge fills more of it; two views whose discs lie apart
    # cannot overlap (the neighbourhood walk's test of most views it refuses).
    disc_xyr: FloatArray = field(init=False)
    version: int = field(init=False, default=0)  # bumped by every :meth:`close`
    # (version, {min size: indices}): the open frontier vertices worth a flight, see frontiers.py
    # (a route's search asks each keyframe at two sizes in turn: one memo each)
    targetable_memo: tuple[int, dict[float, NDArray[np.intp]]] | None = field(init=False, default=None)
    open_memo: tuple[int, NDArray[np.intp]] | None = field(init=False, default=None)
    wall_facts_memo: tuple[int, _WallFacts] | None = field(init=False, default=None)
    # every vertex's _past_end_m and _loose_limit (the polygon's and its map's params: computed once)
    past_end_m: FloatArray | None = field(init=False, default=None)
    loose_limit: NDArray[np.bool_] | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        self.kinds = self.polygon.kinds.copy()
        self.radius_m = float(np.max(np.linalg.norm(self.polygon.vertices_xy, axis=1)))
        self.walls = self.polygon.obstacle_segments()
        self.wall_runs = _wall_runs(self.walls)
        self.open_edges = self.polygon.open_segments()
        self.corners_xy = shapely.get_coordinates(self.polygon.shape)
        centre = (self.corners_xy.min(axis=0) + self.corners_xy.max(axis=0)) / 2.0
        reach = float(np.max(np.hypot(*(self.corners_xy - centre).T)))
        self.disc_xyr = np.array([centre[0], centre[1], reach])

    def open_frontier_indices(self) -> NDArray[np.intp]:
        """The open frontier vertices (read-only, memoised until the next :meth:`close`)."""
        memo = self.open_memo
        if memo is None or memo[0] != self.version:
            idx = np.flatnonzero(self.kinds == KIND_FRONTIER)
            idx.flags.writeable = False
            memo = self.open_memo = (self.version, idx)
        return memo[1]

    def close(self, indices: NDArray[np.intp], kind: VertexKind = VertexKind.FREE) -> None:
        """Type these frontier vertices free (the space beyond them was seen) or obstacle (they
        lie on a wall another view saw): the only change a vertex ever sees, frontiers close and
        nothing reopens. Counts the change so memos of the open set know."""
        if indices.size:
            self.kinds[indices] = kind
            self.version += 1

    def beyond_points(self, indices: NDArray[np.intp], offset_m: float) -> FloatArray:
        """Points just outside the polygon at the given vertices, in this keyframe's frame."""
        return self.polygon.vertices_xy[indices] + offset_m * self.polygon.outward_xy[indices]


@dataclass(frozen=True, slots=True)
class _WallFacts:
    """What :meth:`LocalMap._close_at_walls` asks of a keyframe's open frontier vertices, in its
    own frame: gathered once per :meth:`Keyframe.close`, not per neighbour per new view."""

    indices: NDArray[np.intp]
    points_xy: FloatArray
    on_shadow: NDArray[np.bool_]
    snap_m: FloatArray
    past_end_m: FloatArray
    loose_limit: NDArray[np.bool_]


def _wall_facts(kf: Keyframe, p: MapParams) -> _WallFacts:
    """The keyframe's :class:`_WallFacts` (memoised until its next :meth:`Keyframe.close`)."""
    memo = kf.wall_facts_memo
    if memo is not None and memo[0] == kf.version:
        return memo[1]
    if kf.past_end_m is None or kf.loose_limit is None:
        every = np.arange(kf.kinds.size)
        kf.past_end_m, kf.loose_limit = _past_end_m(kf, every, p), _loose_limit(kf, every)
    idx = kf.open_frontier_indices()
    poly = kf.polygon
    facts = _WallFacts(
        idx,
        poly.vertices_xy[idx],
        poly.on_shadow[idx],
        _snaps_m(poly.at_range_limit[idx], p.wall_snap_m, p.range_limit_snap_m),
        kf.past_end_m[idx],
        kf.loose_limit[idx],
    )
    kf.wall_facts_memo = (kf.version, facts)
    return facts


# The neighbourhood walk's overlap test asks every this-many-th corner of a view first.
_CORNER_STRIDE = 8


def _any_corner_inside(shape: shapely.Polygon, poses: FloatArray, corners: list[FloatArray]) -> NDArray[np.bool_]:
    """For each view (its polygon's corners, moved by its pose: rows of x, y, yaw): whether any
    corner lies inside ``shape``. Every ``_CORNER_STRIDE``-th corner is asked first, and only the
    views none of those settles are asked for all their corners: most neighbours overlap a lot,
    and the containment test of every corner was a tenth of the dearest steps (apartment seed 1)."""
    inside = _any_inside(shape, poses, [c[::_CORNER_STRIDE] for c in corners])
    rest = np.flatnonzero(~inside)
    if rest.size:
        inside[rest] = _any_inside(shape, poses[rest], [corners[i] for i in rest])
    return inside


def _any_inside(shape: shapely.Polygon, poses: FloatArray, corners: list[FloatArray]) -> NDArray[np.bool_]:
    """Whether any of each view's corners (moved by its pose) lies inside ``shape``."""
    pts = apply_grouped(poses, corners)
    owner = np.repeat(np.arange(len(corners)), [c.shape[0] for c in corners])
    hits = np.bincount(owner, shapely.contains_xy(shape, pts[:, 0], pts[:, 1]), minlength=len(corners))
    return np.asarray(hits > 0, dtype=bool)


def _wall_runs(walls: FloatArray) -> FloatArray:
    """(M, 2): how far each edge's wall (the run of edges joined end to start, as the polygon
    gives them) runs on before the edge's start and after its end, along the edges."""
    out = np.zeros((walls.shape[0], 2))
    if walls.shape[0] == 0:
        return out
    length = np.hypot(*(walls[:, 1] - walls[:, 0]).T)
    starts_run = np.concatenate(([True], np.any(walls[1:, 0] != walls[:-1, 1], axis=1)))
    run = np.cumsum(starts_run) - 1
    first = np.flatnonzero(starts_run)
    last = np.concatenate((first[1:], [walls.shape[0]])) - 1
    start_m = np.cumsum(length) - length  # each edge's start, along all edges in turn
    out[:, 0] = start_m - start_m[first][run]
    out[:, 1] = (start_m + length)[last][run] - (start_m + length)
    return out


def _segments_geometry(segments: FloatArray) -> shapely.MultiLineString:
    """Segments (M, 2, 2) as one geometry, built straight from the coordinates (no object per
    segment first: half the time, for a view's 1500 walls)."""
    if segments.shape[0] == 0:
        return shapely.MultiLineString()
    coords = np.ascontiguousarray(segments, dtype=np.float64).reshape(-1, 2)
    offsets = (np.arange(0, coords.shape[0] + 1, 2), np.array([0, segments.shape[0]]))
    geometry: shapely.MultiLineString = shapely.from_ragged_array(
        shapely.GeometryType.MULTILINESTRING, coords, offsets
    )[0]
    return geometry


@dataclass(slots=True)
class LocalView:
    """The neighbourhood of one keyframe expressed in that keyframe's frame (cached)."""

    keyframe_id: int
    poses: dict[int, Pose2]  # pose of each neighbour (and itself) in this frame
    shapes: NDArray[np.object_]  # the neighbourhood's polygons in this frame, in ``poses`` order
    walls_xy: FloatArray  # every obstacle edge seen in the neighbourhood (M, 2, 2), its own first
    obstacles: shapely.MultiLineString  # the same edges as one geometry, for distance queries
    walls_seen_from_xy: FloatArray  # (M, 2): the origin of the view that saw each edge
    wall_starts: NDArray[np.intp]  # where each keyframe's edges start in ``walls_xy`` (``poses`` order, and the end)
    _grown: shapely.Geometry | None = None
    # neighbour -> whether it disagrees with the keyframe (LocalMap._disagreeing), asked lazily
    disagrees: dict[int, bool] = field(default_factory=dict)

    @property
    def grown(self) -> shapely.Geometry:
        """The union of the neighbourhood's polygons (known free space), built on first use: the
        union is the dearest part of a view, and only paths (:meth:`covers`) and the free-space
        grid need it; points ask :meth:`holds`.
        Snap rounding: robust, and without it near-coincident edges of overlapping views leave
        sliver holes that fail path checks (tried: twice as fast, office 8 % slower to explore)."""
        if self._grown is None:
            self._grown = shapely.union_all(self.shapes, grid_size=1e-3)
            shapely.prepare(self._grown)
        return self._grown

    def covers(self, geometry: shapely.Geometry) -> bool:
        """Whether the grown polygon covers the geometry (a path). One view that covers it alone
        settles it without the union (the dearest part of a view: 9 ms for 50 views); only
        a path that crosses from one view into another needs the union."""
        if self._grown is None:
            minx, miny, maxx, maxy = geometry.bounds
            b = shapely.bounds(self.shapes)
            maybe = np.flatnonzero((b[:, 0] <= minx) & (b[:, 1] <= miny) & (b[:, 2] >= maxx) & (b[:, 3] >= maxy))
            if maybe.size and shapely.covers(self.shapes[maybe], geometry).any():
                return True
        return bool(self.grown.covers(geometry))

    def holds(self, points_xy: FloatArray, among: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
        """Which points lie inside one of the neighbourhood's polygons (inside the grown one), or
        only of those ``among`` marks (one flag per polygon, in ``poses`` order)."""
        if points_xy.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        if among is None and self._grown is not None:
            return np.asarray(shapely.contains_xy(self._grown, points_xy[:, 0], points_xy[:, 1]), dtype=bool)
        shapes = self.shapes if among is None else self.shapes[among]
        inside = shapely.contains_xy(shapes[:, None], points_xy[None, :, 0], points_xy[None, :, 1])
        return np.asarray(inside.any(axis=0), dtype=bool)


class LocalMap:
    """Keyframes, their polygons and the pose graph; answers frontier and free-space queries."""

    def __init__(self, params: MapParams | None = None) -> None:
        self.params = params or MapParams()
        self.graph = PoseGraph()
        self.keyframes: dict[int, Keyframe] = {}
        # (parent, child) -> the way the vehicle flew from the parent to where it took the child,
        # (K, 2) in the parent's frame, ends left out: an odometry edge is a leg flown once.
        self._flown: dict[tuple[int, int], FloatArray] = {}
        self._neighbours: dict[int, dict[int, Pose2]] = {}
        self._hops: dict[int, dict[int, int]] = {}  # hops along the path each neighbour was placed by
        self._views: dict[int, LocalView] = {}
        self._next_id = 0
        self._radii_m: FloatArray = np.zeros(0)  # by id (ids count up from 0): an array, indexed per walk level
        self._discs: FloatArray = np.zeros((0, 3))  # each view's Keyframe.disc_xyr, by id likewise
        # keyframe -> its view when its frontiers were last judged for slivers, and which were
        self._sliver_judged: dict[int, tuple[LocalView, set[int]]] = {}
        self.loop_closures = 0
        self.slivers_closed = 0

    def __len__(self) -> int:
        return len(self.keyframes)

    def add_keyframe(
        self,
        stamp_s: float,
        odom_pose: Pose2,
        polygon: FovPolygon,
        parent: tuple[int, Pose2] | None = None,
        flown_xy: FloatArray | None = None,
    ) -> Keyframe:
        """Add a keyframe, joined by an odometry edge to ``parent = (id, pose of new in parent)``,
        and close the frontiers its view and its neighbours' views cover. ``flown_xy`` is the way
        the vehicle flew from the parent (points in its frame, see :meth:`flown_between`)."""
        kf_id = self._next_id
        self._next_id += 1
        kf = Keyframe(kf_id, stamp_s, odom_pose, polygon)
        self.keyframes[kf_id] = kf
        self._radii_m = np.append(self._radii_m, kf.radius_m)  # a copy per keyframe, not per query
        self._discs = np.vstack((self._discs, kf.disc_xyr))
        self.graph.add_keyframe(kf_id)
        self._neighbours[kf_id] = {}
        self._hops[kf_id] = {}
        if parent is not None:
            self.graph.add_edge(parent[0], kf_id, parent[1], EdgeType.ODOMETRY)
            if flown_xy is not None and flown_xy.shape[0]:
                self._flown[(parent[0], kf_id)] = np.asarray(flown_xy, dtype=np.float64).reshape(-1, 2)
        self._integrate(kf_id)
        return kf

    def flown_between(self, from_id: int, to_id: int) -> FloatArray | None:
        """The way flown along the odometry edge between two keyframes, from ``from_id`` towards
        ``to_id``, in ``from_id``'s frame (None when the edge has none): where a straight leg
        between them is blocked (one taken out of the other's sight), the vehicle can fly it back."""
        ahead = self._flown.get((from_id, to_id))
        if ahead is not None:
            return ahead
        back = self._flown.get((to_id, from_id))
        if back is None:
            return None
        return self.pose_in(from_id, to_id).apply(back[::-1])

    def add_loop_closure(self, earlier_id: int, later_id: int, earlier_to_later: Pose2) -> None:
        """Join two keyframes by a loop-closure edge and close what their views now share."""
        if earlier_id not in self.keyframes or later_id not in self.keyframes:
            raise GraphError(f"loop closure names unknown keyframe {earlier_id} or {later_id}")
        self.graph.add_edge(earlier_id, later_id, earlier_to_later, EdgeType.LOOP_CLOSURE)
        self.loop_closures += 1
        self._integrate(later_id)

    def neighbourhood(self, keyframe_id: int) -> dict[int, Pose2]:
        """Neighbours of a keyframe with their pose in its frame (the keyframe itself excluded)."""
        return dict(self._neighbours[keyframe_id])

    def view(self, keyframe_id: int) -> LocalView:
        """The keyframe's neighbourhood, grown polygon and obstacles, in its frame (cached).

        Building a view applies eq. 2.15 over its grown polygon: every open frontier of the
        neighbourhood whose space just beyond lies inside the grown free space is closed.
        """
        cached = self._views.get(keyframe_id)
        if cached is not None:
            return cached
        view = self._build_view(keyframe_id)
        self._close_in_grown(view)
        return view

    def _build_view(self, keyframe_id: int) -> LocalView:
        """The view's geometry (no frontier closing), cached: every neighbour moved into the
        keyframe's frame in one vectorised pass (their union waits for :attr:`LocalView.grown`)."""
        poses = {keyframe_id: Pose2.identity(), **self._neighbours[keyframe_id]}
        frames = list(poses.values())
        kfs = [self.keyframes[k] for k in poses]
        shapes = move_each(frames, np.array([kf.polygon.shape for kf in kfs], dtype=object))
        # Rounding in the move can make a near-degenerate ring self-touch; repair before union.
        bad = ~shapely.is_valid(shapes)
        if bad.any():
            shapes[bad] = shapely.make_valid(shapes[bad])
        # Prepared once here: a view's polygons answer many point tests (closing, the planner's
        # checks), and an unprepared polygon is prepared again for each point it is asked about.
        shapely.prepare(shapes)
        walls_xy = apply_grouped(frames, [kf.walls.reshape(-1, 2) for kf in kfs]).reshape(-1, 2, 2)
        obstacles = _segments_geometry(walls_xy)
        shapely.prepare(obstacles)
        counts = [kf.walls.shape[0] for kf in kfs]
        seen_from = np.repeat([(f.x_m, f.y_m) for f in frames], counts, axis=0)
        starts = np.concatenate(([0], np.cumsum(counts))).astype(np.intp)
        view = LocalView(keyframe_id, poses, shapes, walls_xy, obstacles, seen_from.reshape(-1, 2), starts)
        self._views[keyframe_id] = view
        return view

    def close_seen_from(self, frame_id: int, keyframe_id: int, indices: NDArray[np.intp]) -> NDArray[np.bool_]:
        """Eq. 2.15 for some frontier vertices of any keyframe against ``frame_id``'s grown view,
        even when that keyframe is not in its neighbourhood (the vehicle went there and looked).
        Returns which of them were closed."""
        view = self.view(frame_id)
        kf = self.keyframes[keyframe_id]
        pose = view.poses.get(keyframe_id) or self.pose_in(frame_id, keyframe_id)
        seen = view.holds(pose.apply(kf.beyond_points(indices, self.params.closing_offset_m)))
        kf.close(indices[seen])
        return seen

    def close_through_graph(self, keyframe_id: int, since_id: int = 0) -> int:
        """Eq. 2.15 for a keyframe's open frontiers against every view the pose graph reaches, not
        only its neighbourhood: a view on the far side of a block, joined to this one only by a
        long chain, may have seen beyond them. Only views from ``since_id`` on are tested (the
        caller knows the older ones were, along the same paths). Returns how many closed.

        A vertex closes when it, or the point just beyond it, lies inside another view at least
        a depth away from that view's open edges (where its free space ends at space it did not
        see); the depth grows with the chain's hops, for the drift along it. Its walls do not
        count: a vertex by a wall the other view saw has nothing beyond it but that wall, and
        asking for space deeper beyond such a vertex (as along its outward normal) asked for
        space inside the wall, so the frontiers a view leaves along a wall it sees at a grazing
        angle stayed open and were flown to one by one after the room was seen. A vertex that
        close to a wall such a view saw (``graph_wall_snap_m``) closes too, as one by a wall of
        its neighbourhood does: the views that saw that wall closer are often not neighbours.
        A view ``misplaced_min_hops`` or more along that disagrees with the keyframe as a
        misplaced neighbour does (:meth:`_disagree`) closes nothing, whatever its margin."""
        kf = self.keyframes[keyframe_id]
        idx = kf.open_frontier_indices()
        if idx.size == 0:
            return 0
        p = self.params
        reach = self.graph.reached(keyframe_id, self._chain_hops())
        ids, hops, poses = reach.ids, reach.hops, reach.poses
        radii = self._radii_m[ids]
        test = (ids >= since_id) & (ids != keyframe_id) & (hops <= p.chain_max_hops)
        test &= np.hypot(poses[:, 0], poses[:, 1]) <= kf.radius_m + radii
        test[test] &= ~np.isin(ids[test], np.fromiter(self._neighbours[keyframe_id], dtype=np.intp))
        if not test.any():
            return 0
        ids, hops, poses = ids[test], hops[test], poses[test]
        shapes = np.array([self.keyframes[int(k)].polygon.shape for k in ids], dtype=object)
        depth = np.maximum(
            p.closing_depth_m - p.closing_offset_m, np.minimum(p.chain_max_margin_m, p.chain_margin_per_hop_m * hops)
        )
        # Past the margin's cap the margin no longer covers the drift, and a view so far along
        # the chain may lie across a wall from where it was taken (a 1.5 m spiral corridor's
        # views 50 hops on lay 2.6 m off, and closed the next corridor's frontiers as seen):
        # such a view closes nothing (``chain_closes_past_cap``), or, with that set, only when
        # it does not disagree with the keyframe (below). Not without loop closures: there every
        # revisit is such a chain, and closing through it is what lets exploration end at all
        # (the trade-off ``close_new_through_graph`` makes).
        past_cap = (p.chain_margin_per_hop_m * hops > p.chain_max_margin_m) & (not p.close_new_through_graph)
        if past_cap.any() and not p.chain_closes_past_cap:
            keep = ~past_cap
            ids, hops, poses, shapes, depth = ids[keep], hops[keep], poses[keep], shapes[keep], depth[keep]
            past_cap = past_cap[keep]
            if ids.size == 0:
                return 0
        # Every open vertex and its point just beyond, moved into every view's frame at once.
        v = kf.polygon.vertices_xy[idx]
        pts = np.stack((v, v + p.closing_offset_m * kf.polygon.outward_xy[idx]))  # (2, vertices, 2)
        d = pts[None] - poses[:, None, None, :2]
        c, s = np.cos(poses[:, 2])[:, None, None], np.sin(poses[:, 2])[:, None, None]
        x, y = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]  # (views, 2, vertices)
        inside = shapely.contains_xy(shapes[:, None, None], x, y)
        # A wall is lent only by a view the margin covers: one placed past its cap may lie 2 m
        # off, and a spiral corridor's way on closed as the wall of the corridor next to it
        # (a small view, too small to be found misplaced).
        walls = [
            np.zeros((0, 2)) if beyond else self.keyframes[int(k)].walls.reshape(-1, 2)
            for k, beyond in zip(ids, past_cap, strict=True)
        ]
        wall_counts = [w.shape[0] // 2 for w in walls]
        segments = apply_grouped(poses, walls).reshape(-1, 2, 2) if any(wall_counts) else np.zeros((0, 2, 2))
        seen_from = np.repeat(poses[:, :2], wall_counts, axis=0)
        shadow = kf.polygon.on_shadow[idx]
        snap = p.graph_wall_snap_m > 0.0 and segments.shape[0] > 0
        near = _near_walls(v, shadow, segments, seen_from, p.graph_wall_snap_m, p.wall_behind_m) if snap else None
        # No view far along closes anything, nor lends a wall, when it disagrees with this keyframe
        # as a misplaced neighbour does (walls deep in each other's free space), past the cap or
        # within it, however the chain's drift compares with the margin: views of the room beside
        # a corridor, 18-20 hops on and placed 0.8-1.9 m off across its wall, closed the
        # corridor's way on as seen (campus seed 9 `complete` at coverage 0.88, in a variant).
        # Not without loop closures (as past the cap): there every revisit is such a chain.
        owner = np.repeat(np.arange(ids.size), wall_counts)
        lends = inside.any(axis=(1, 2))
        if near is not None:
            lends[np.unique(owner[near.any(axis=0)])] = True
        far = lends & (hops >= p.misplaced_min_hops) & (not p.close_new_through_graph)
        doubtful = np.flatnonzero(far)
        if doubtful.size:
            at = [Pose2(float(px), float(py), float(pt)) for px, py, pt in poses[doubtful]]
            their_walls = [self.keyframes[int(ids[i])].walls for i in doubtful]
            placed = apply_grouped(at, [w.reshape(-1, 2) for w in their_walls]).reshape(-1, 2, 2)
            placed_walls = np.split(placed, np.cumsum([w.shape[0] for w in their_walls])[:-1])
            found = self._disagree(keyframe_id, kf.polygon.shape, move_each(at, shapes[doubtful]), placed_walls)
            bad = doubtful[found]
            if bad.size:
                inside[bad] = False
                if near is not None:
                    near[:, np.isin(owner, bad)] = False
        seen = np.zeros(idx.size, dtype=bool)
        for j in np.flatnonzero(inside.any(axis=(1, 2))):  # then the depth, view by view
            ask = inside[j] & ~seen
            if not ask.any():
                continue
            deep = np.ones(np.count_nonzero(ask), dtype=bool)
            edges = self.keyframes[int(ids[j])].open_edges
            if edges.shape[0]:
                q = np.column_stack((x[j][ask], y[j][ask]))
                deep = point_segment_distances(q, edges).min(axis=1) >= depth[j]
            hit = np.zeros(ask.shape, dtype=bool)
            hit[ask] = deep
            seen |= hit.any(axis=0)
        # The vertices still open, against those views' walls (moved into this keyframe's frame).
        on_wall = np.zeros(idx.size, dtype=bool) if near is None else near.any(axis=1) & ~seen
        kf.close(idx[seen])
        kf.close(idx[on_wall], VertexKind.OBSTACLE)
        return int(np.count_nonzero(seen | on_wall))

    def unjudged_slivers(
        self, keyframe_id: int, indices: NDArray[np.intp], frame_id: int | None = None
    ) -> NDArray[np.intp]:
        """Those of the keyframe's open frontier vertices not yet judged (:meth:`close_slivers`)
        in the view they would be judged in now (a view is rebuilt when its neighbourhood
        changes)."""
        kf = self.keyframes[keyframe_id]
        if self.params.slivers.reach_m <= 0.0 or indices.size == 0:
            return indices[:0]
        indices = indices[kf.kinds[indices] == KIND_FRONTIER]
        judged = self._sliver_judged.get(keyframe_id)
        view = self._judging_view(keyframe_id, frame_id, build=False)
        if judged is None or view is None or judged[0] is not view:
            return indices
        return indices[~np.isin(indices, np.fromiter(judged[1], dtype=np.intp))]

    def close_slivers(
        self, keyframe_id: int, indices: NDArray[np.intp], frame_id: int | None = None
    ) -> NDArray[np.bool_]:
        """Close those of these open frontier vertices of the keyframe whose unseen space is only
        a sliver (slivers.py), judged without the views that disagree with the judging view's
        keyframe: in ``frame_id``'s view when it is built and holds the keyframe agreeing with it
        (the planner's current view: no view to build), else in the keyframe's own. Returns which
        were closed."""
        kf = self.keyframes[keyframe_id]
        view = self._judging_view(keyframe_id, frame_id, build=True)
        assert view is not None
        judged = self._sliver_judged.get(keyframe_id)
        if judged is None or judged[0] is not view:
            judged = self._sliver_judged[keyframe_id] = (view, set())
        judged[1].update(indices.tolist())
        hit = np.zeros(indices.size, dtype=bool)
        ask = kf.kinds[indices] == KIND_FRONTIER  # building the view may have closed some
        if not ask.any():
            return hit
        idx = indices[ask]
        pose = view.poses[keyframe_id]
        vertices = pose.apply(kf.polygon.vertices_xy[idx])
        # Only the views round the vertices judge (no other reaches a window's cells, walls
        # rounded into its edge cells included), and only those that agree with the view's
        # keyframe, however few hops away: a view one bad loop closure misplaced may cover
        # unseen space as seen.
        p = self.params.slivers
        reach = (p.reach_m + p.cell_m) * math.sqrt(2.0)
        lo, hi = vertices.min(axis=0) - reach, vertices.max(axis=0) + reach
        b = shapely.bounds(view.shapes)
        ids = list(view.poses)
        keep = np.all((b[:, 2:] >= lo) & (b[:, :2] <= hi), axis=1)
        bad = self._disagreeing(view, [ids[i] for i in np.flatnonzero(keep)])
        if bad:
            keep &= ~np.isin(np.array(ids), list(bad))
        per_view = [self.keyframes[k].walls.shape[0] for k in ids]
        walls = view.walls_xy[np.repeat(keep, per_view)]
        hit[ask] = sliver_vertices(vertices, pose.rotate(kf.polygon.outward_xy[idx]), view.shapes[keep], walls, p)
        kf.close(indices[hit])
        self.slivers_closed += int(np.count_nonzero(hit))
        return hit

    def _judging_view(self, keyframe_id: int, frame_id: int | None, build: bool) -> LocalView | None:
        """The view a keyframe's vertices are judged for slivers in: ``frame_id``'s, if built and
        it holds the keyframe and agrees with it (:meth:`_disagreeing`), else the keyframe's own
        (built if asked, else None when it is not)."""
        if frame_id is not None and frame_id != keyframe_id:
            current = self._views.get(frame_id)
            if current is not None and keyframe_id in current.poses and not self._disagreeing(current, [keyframe_id]):
                return current
        return self.view(keyframe_id) if build else self._views.get(keyframe_id)

    def _chain_hops(self) -> int:
        """The longest chain :meth:`close_through_graph` may close through: ``chain_max_hops``,
        or (where views past the drift margin's cap close nothing) the last hop the cap covers."""
        p = self.params
        if p.close_new_through_graph or p.chain_closes_past_cap or p.chain_margin_per_hop_m <= 0.0:
            return p.chain_max_hops
        return min(p.chain_max_hops, int(p.chain_max_margin_m / p.chain_margin_per_hop_m) + 1)

    def close_frontiers(self, keyframe_id: int, indices: NDArray[np.intp], kind: VertexKind = VertexKind.FREE) -> None:
        """Close frontier vertices: looked at, nothing beyond them to explore (``kind`` obstacle
        when a wall was seen right there)."""
        kf = self.keyframes[keyframe_id]
        kf.close(indices[kf.kinds[indices] == KIND_FRONTIER], kind)

    def open_frontier_count(self) -> int:
        return int(sum(np.count_nonzero(kf.kinds == KIND_FRONTIER) for kf in self.keyframes.values()))

    def pose_in(self, frame_id: int, keyframe_id: int) -> Pose2:
        """Pose of a keyframe in another's frame: the cached neighbourhood or the graph path."""
        if frame_id == keyframe_id:
            return Pose2.identity()
        cached = self._neighbours[frame_id].get(keyframe_id)
        return cached if cached is not None else self.graph.relative(frame_id, keyframe_id)

    # -- internals ---------------------------------------------------------------------------

    def _find_neighbourhood(self, kf_id: int) -> dict[int, tuple[Pose2, int]]:
        kf = self.keyframes[kf_id]
        shape = kf.polygon.shape

        def overlaps(ids: list[int], rows: FloatArray) -> NDArray[np.bool_]:
            """Which of these views, at these poses (rows of x, y, yaw), overlap this one (all at once)."""
            radii = self._radii_m[ids]
            out: NDArray[np.bool_] = np.hypot(rows[:, 0], rows[:, 1]) <= kf.radius_m + radii
            near = np.flatnonzero(out)
            if near.size == 0:
                return out
            # Discs that lie apart (by more than any rounding) settle most views refused.
            discs = self._discs[np.asarray(ids)[near]]
            centres = apply_each(rows[near], discs[:, :2], np.arange(near.size))
            gap = np.hypot(*(centres - kf.disc_xyr[:2]).T) - discs[:, 2] - kf.disc_xyr[2]
            out[near[gap > 1e-6]] = False
            near = near[gap <= 1e-6]
            if near.size == 0:
                return out
            # A corner of the other view inside this one settles it without building the moved
            # polygon (most neighbours overlap a lot); the exact test only for the rest.
            corners = [self.keyframes[ids[i]].corners_xy for i in near]
            inside = _any_corner_inside(shape, rows[near], corners)
            rest = near[~inside]
            if rest.size:
                shapes = np.array([self.keyframes[ids[i]].polygon.shape for i in rest], dtype=object)
                out[rest] = shapely.intersects(shape, move_each(rows[rest], shapes))
            return out

        visits = self.graph.walk_levels(
            kf_id,
            overlaps,
            self.params.neighbourhood_bridge_hops,
            self.params.neighbourhood_still_m,
            ahead=self.params.neighbourhood_ask_ahead,
        )
        return {v.keyframe_id: (v.pose_in_start, v.hops) for v in visits[1:]}

    def _integrate(self, kf_id: int) -> None:
        """(Re)compute a keyframe's neighbourhood, then close the frontiers it shares."""
        found = self._find_neighbourhood(kf_id)
        self._neighbours[kf_id] = {k: pose for k, (pose, _) in found.items()}
        self._hops[kf_id] = {k: hops for k, (_, hops) in found.items()}
        self._views.pop(kf_id, None)
        for other_id, (pose, hops) in found.items():
            self._neighbours[other_id][kf_id] = pose.inverse()
            self._hops[other_id][kf_id] = hops
            self._views.pop(other_id, None)
        view = self._build_view(kf_id)
        self._close_at_walls(kf_id, view)
        self._close_in_grown(view)
        if self.params.close_new_through_graph:
            self.close_through_graph(kf_id)

    def _close_in_grown(self, view: LocalView) -> None:
        """Eq. 2.15: a frontier vertex whose outside lies in the grown free space is free (every
        open vertex of the neighbourhood in one query), when the grown free space also reaches
        ``closing_depth_m`` beyond it, or a wall does.

        The depth is for drift. A view that saw the space beyond through a door, at a grazing
        angle, holds only a sliver of it; a few tenths of a metre of pose error slide that sliver
        over the vertices of other views' frontiers, and theirs over its own, until every vertex
        along an unexplored corridor was closed (an apartment's corridor, never flown: coverage
        0.77). A sliver is not deep; space another view really saw beyond a frontier is."""
        kfs = [self.keyframes[k] for k in view.poses]
        idx = [kf.open_frontier_indices() for kf in kfs]
        if not any(i.size for i in idx):
            return
        p = self.params
        poses = list(view.poses.values())

        def beyond(offset_m: float) -> FloatArray:
            """Every open vertex's point ``offset_m`` outside it, in the view's frame."""
            return apply_grouped(poses, [kf.beyond_points(i, offset_m) for kf, i in zip(kfs, idx, strict=True)])

        near = beyond(p.closing_offset_m)
        seen = view.holds(near)
        if p.closing_depth_m > p.closing_offset_m and seen.any():
            deep = beyond(p.closing_depth_m)
            check = np.flatnonzero(seen)
            deep_seen = view.holds(deep[check])
            owner = np.repeat(np.arange(len(kfs)), [i.size for i in idx])
            misplaced = self._misplaced(view, owner[check], np.concatenate((near[check], deep[check])))
            if misplaced.any():  # neither closed nor closing: held by the other views alone
                held = ~misplaced[owner[check]] & view.holds(near[check], among=~misplaced)
                deep_seen &= view.holds(deep[check], among=~misplaced)
                seen[check[~held]] = False
                check = check[held]
                deep_seen = deep_seen[held]
            shallow = check[~deep_seen]
            if shallow.size and not view.obstacles.is_empty:
                walled = shapely.intersects(
                    shapely.linestrings(np.stack((near[shallow], deep[shallow]), axis=1)), view.obstacles
                )
                seen[shallow[~walled]] = False
            else:
                seen[shallow] = False
        _close_where(kfs, idx, seen)

    def _misplaced(self, view: LocalView, owners: NDArray[np.intp], points_xy: FloatArray) -> NDArray[np.bool_]:
        """Which of the view's keyframes (``view.poses`` order; never its own) were placed by a
        path of ``misplaced_min_hops`` or more and disagree with its own keyframe (see
        :meth:`_disagreeing`). Returns are exact in their own keyframe's frame; placed right, one
        view's walls lie on or beyond another's edge. Placed by a drifted chain of the graph,
        they do not. Only asked of those that matter to the closing at hand: the owners (indices
        in ``view.poses`` order) of the vertices it closes, and the views holding one of its
        ``points_xy``; the rest count as agreeing (their answer would change nothing)."""
        hops = self._hops[view.keyframe_id]
        ids = list(view.poses)
        far = np.array([hops.get(k, 0) >= self.params.misplaced_min_hops for k in ids], dtype=bool)
        out = np.zeros(len(ids), dtype=bool)
        if not far.any():
            return out
        ask = np.zeros(len(ids), dtype=bool)
        ask[owners] = True
        rest = np.flatnonzero(far & ~ask)
        if rest.size and points_xy.shape[0]:
            inside = shapely.contains_xy(view.shapes[rest][:, None], points_xy[None, :, 0], points_xy[None, :, 1])
            ask[rest[inside.any(axis=1)]] = True
        ask &= far
        if not ask.any():
            return out
        bad = self._disagreeing(view, [ids[i] for i in np.flatnonzero(ask)])
        return np.array([k in bad for k in ids], dtype=bool)

    def _disagreeing(self, view: LocalView, ids: list[int]) -> set[int]:
        """Which of these neighbours disagree with the view's own keyframe by more than
        ``misplaced_depth_m`` (:meth:`_disagree`), each asked once per view."""
        todo = [k for k in dict.fromkeys(ids) if k != view.keyframe_id and k not in view.disagrees]
        if todo:
            order = {k: i for i, k in enumerate(view.poses)}
            at = np.array([order[k] for k in todo], dtype=np.intp)
            # Their walls as the view placed them (the same numbers as moving them again).
            walls = [view.walls_xy[view.wall_starts[i] : view.wall_starts[i + 1]] for i in at.tolist()]
            found = self._disagree(view.keyframe_id, view.shapes[0], view.shapes[at], walls)
            view.disagrees.update(zip(todo, found.tolist(), strict=True))
        return {k for k in ids if view.disagrees.get(k, False)}

    def _disagree(
        self,
        keyframe_id: int,
        own_shape: shapely.Geometry,
        shapes: NDArray[np.object_],
        walls: list[FloatArray],
    ) -> NDArray[np.bool_]:
        """Which of the other views (``shapes`` and their ``walls`` already placed in the
        keyframe's frame) disagree with the keyframe by more than
        ``misplaced_depth_m``: its walls (ends and midpoints) that deep inside theirs, or theirs
        inside its own polygon ``own_shape``. (Not a deeper tolerance for a longer chain: in a
        corridor nothing lies deeper inside a view than half the corridor's width.)"""
        out = np.zeros(len(shapes), dtype=bool)
        tol = self.params.misplaced_depth_m

        def probes(segments: FloatArray) -> FloatArray:
            return np.concatenate((segments[:, 0], segments[:, 1], segments.mean(axis=1)))

        own = self.keyframes[keyframe_id].walls
        if own.shape[0]:
            pts = probes(own)
            rows, cols = np.nonzero(shapely.contains_xy(shapes[:, None], pts[None, :, 0], pts[None, :, 1]))
            # Each view's boundary once (a probe inside one view is inside it at many probes).
            users, at = np.unique(rows, return_inverse=True)
            depth = shapely.distance(shapely.boundary(shapes[users])[at], shapely.points(pts[cols]))
            out[rows[depth > tol]] = True
        if any(w.shape[0] for w in walls):
            placed = np.concatenate(walls)
            pts, who = probes(placed), np.tile(np.repeat(np.arange(len(walls)), [w.shape[0] for w in walls]), 3)
            inside = shapely.contains_xy(own_shape, pts[:, 0], pts[:, 1])
            depth = shapely.distance(shapely.boundary(own_shape), shapely.points(pts[inside]))
            out[who[inside][depth > tol]] = True
        return out

    def _chain_drift_m(self, kf_id: int, others: list[int]) -> FloatArray:
        """The drift the chain from the keyframe to each of these neighbours allows, for those
        ``misplaced_min_hops`` or more along it; -inf for nearer ones (not asked)."""
        p = self.params
        hops_to = self._hops[kf_id]
        hops = np.array([hops_to.get(k, 0) for k in others], dtype=np.float64)
        drift = np.minimum(p.chain_max_margin_m, p.chain_margin_per_hop_m * hops)
        return np.where(hops >= p.misplaced_min_hops, drift, -math.inf)

    def _close_at_walls(self, kf_id: int, view: LocalView) -> None:
        """A frontier vertex lying on a wall another view saw is no frontier (range noise at the
        sensor's limit leaves such vertices, and nothing beyond them can ever be seen): within
        ``wall_snap_m``, or ``range_limit_snap_m`` for a vertex at the range limit. All in
        the new keyframe's frame (its ``view``): its open vertices against every neighbour's
        walls at once, and every neighbour's open vertices against its own walls.

        Only between views that agree (:meth:`_disagreeing`), however few hops apart: a loop
        closure 0.35 m off placed a view two hops away with a wall across a cave's passage, and
        the passage's frontiers closed on it (cave seed 5: `complete` at coverage 0.52). And a
        range-limit vertex with no wall beside it lies on the wall of a neighbour
        ``misplaced_min_hops`` or more along only where that wall runs on past it by the chain's
        drift (see ``MapParams.misplaced_min_hops``)."""
        kf = self.keyframes[kf_id]
        p = self.params
        own_walls = kf.walls
        mine = _wall_facts(kf, p)
        own = mine.indices
        behind = p.wall_behind_m
        others = list(view.poses)[1:]  # the view's own keyframe comes first, its walls too
        drift = self._chain_drift_m(kf_id, others)
        if own.size:
            theirs = slice(own_walls.shape[0], None)
            per_view = [self.keyframes[k].walls.shape[0] for k in others]
            owner = np.repeat(others, per_view)
            near = _near_walls(
                mine.points_xy,
                mine.on_shadow,
                view.walls_xy[theirs],
                view.walls_seen_from_xy[theirs],
                mine.snap_m,
                behind,
                mine.past_end_m,
                np.where(mine.loose_limit[:, None], np.repeat(drift, per_view)[None, :], -math.inf),
                np.concatenate([np.zeros((0, 2))] + [self.keyframes[k].wall_runs for k in others]),
            )
            if near.any():
                lenders = owner[near.any(axis=0)].tolist()
                bad = self._disagreeing(view, lenders)
                if bad:
                    near[:, np.isin(owner, list(bad))] = False
                kf.close(own[near.any(axis=1)], VertexKind.OBSTACLE)
        if own_walls.shape[0] == 0:
            return
        facts = [_wall_facts(self.keyframes[k], p) for k in others]
        if not any(f.indices.size for f in facts):
            return
        kfs = [self.keyframes[k] for k in others]
        idx = [f.indices for f in facts]
        counts = [i.size for i in idx]
        pts = apply_grouped([view.poses[k] for k in others], [f.points_xy for f in facts])
        shadow = np.concatenate([f.on_shadow for f in facts])
        snap = np.concatenate([f.snap_m for f in facts])
        own_from = np.zeros((own_walls.shape[0], 2))  # seen from this keyframe's origin
        past_end = np.concatenate([f.past_end_m for f in facts])
        loose = np.concatenate([f.loose_limit for f in facts])
        runs_on = np.where(loose, np.repeat(drift, counts), -math.inf)[:, None]
        near_own = _near_walls(pts, shadow, own_walls, own_from, snap, behind, past_end, runs_on, kf.wall_runs)
        on: NDArray[np.bool_] = np.asarray(near_own.any(axis=1))
        if on.any():
            vertex_owner = np.repeat(others, counts)
            bad = self._disagreeing(view, vertex_owner[on].tolist())
            if bad:
                on &= ~np.isin(vertex_owner, list(bad))
        _close_where(kfs, idx, on, VertexKind.OBSTACLE)


def _loose_limit(kf: Keyframe, indices: NDArray[np.intp]) -> NDArray[np.bool_]:
    """Which of these vertices lie at the range limit with no obstacle vertex beside them in
    their own polygon (out in an arc, as in a doorway; not where a wall left the range)."""
    kinds = kf.polygon.kinds
    n = kinds.size
    beside = (kinds[(indices - 1) % n] == KIND_OBSTACLE) | (kinds[(indices + 1) % n] == KIND_OBSTACLE)
    return np.asarray(kf.polygon.at_range_limit[indices] & ~beside, dtype=bool)


def _past_end_m(kf: Keyframe, indices: NDArray[np.intp], p: MapParams) -> FloatArray:
    """How far from a wall's end, where they lie past it, each of these vertices may lie and
    still be on it (see :func:`_near_walls`): ``wall_snap_m`` for a vertex at the range limit
    away from its own view's walls, unbounded for the others. Where its own view saw a wall
    leave the range beside it, the vertex is that wall's end in its view, and a neighbour's view
    of the wall may end as near (session 40's wider snap); in a door seen past its jamb, no wall
    of its own is by it."""
    out = np.full(indices.size, math.inf)
    limit = kf.polygon.at_range_limit[indices]
    if not limit.any():
        return out
    if kf.walls.shape[0] == 0:
        out[limit] = p.wall_snap_m
        return out
    own_wall = point_segment_distances(kf.polygon.vertices_xy[indices[limit]], kf.walls).min(axis=1)
    out[np.flatnonzero(limit)[own_wall > p.range_limit_snap_m]] = p.wall_snap_m
    return out


def _close_where(
    kfs: list[Keyframe], indices: list[NDArray[np.intp]], hit: NDArray[np.bool_], kind: VertexKind = VertexKind.FREE
) -> None:
    """Close (as ``kind``) the vertices ``indices[j]`` of ``kfs[j]`` whose entry in ``hit`` (all
    keyframes' entries one after another) is set."""
    start = 0
    for kf, i in zip(kfs, indices, strict=True):
        kf.close(i[hit[start : start + i.size]], kind)
        start += i.size


def _near_walls(
    points_xy: FloatArray,
    on_shadow: NDArray[np.bool_],
    segments: FloatArray,
    seen_from_xy: FloatArray,
    snap_m: float | FloatArray,
    behind_m: float,
    past_end_m: float | FloatArray = math.inf,
    runs_on_m: FloatArray | None = None,
    wall_runs: FloatArray | None = None,
) -> NDArray[np.bool_]:
    """(N, M): which frontier vertices (``points_xy``) lie on which walls (segments (M, 2, 2), each
    seen from the matching point of ``seen_from_xy``): within ``snap_m`` of it, and, for those on
    a shadow edge (``on_shadow``), not more than ``behind_m`` behind the face its view saw. A
    shadow edge's vertex farther behind lies beyond that wall, hidden behind an occluder: a door
    seen at a shallow angle has its shadow edge run a few tenths of a metre behind the corridor
    wall's face, and closing those vertices as that wall ended runs `complete` with the room
    behind the door unseen (apartment seeds 2 and 4 in session 20). Other vertices (a range
    limit or the field of view's side lying on a wall) snap from either side: drift puts most of
    them a little behind the face, and asking it of them too cost 10 % of the exploration time.

    None lies on a wall whose end it lies past and more than ``past_end_m`` (one for all, or one
    each) from, however wide its snap: the wider snap at the range limit is for drift across a
    wall, and past a jamb's end lies a door. (A door seen only at a grazing angle kept one
    frontier vertex, at the range limit in the doorway, 0.28 m from the jamb's end: closed as
    that wall, courtyard seed 4 ran `complete` at coverage 0.937 in a variant, with the room
    behind unseen. Measured along the wall's line, as until session 63, a doorway's vertex 0.09 m
    past the end of a 0.3 m edge across a jamb's corner, and 0.15 m beside its line, closed on it:
    lshape seed 5 ran `complete` at coverage 0.953, the room behind the door unseen.)

    With ``runs_on_m`` ((N, M) or (N, 1); -inf where not asked) and each segment's ``wall_runs``
    (see :func:`_wall_runs`), a vertex lies on a segment only where its wall runs on past the
    vertex, both ways along it, farther than that."""
    out = np.zeros((points_xy.shape[0], segments.shape[0]), dtype=bool)
    if segments.shape[0] == 0 or points_xy.shape[0] == 0:
        return out
    # Only the segments whose bounding box comes within the snap of the points' box can be near.
    snap = np.broadcast_to(np.asarray(snap_m, dtype=np.float64), points_xy.shape[:1])
    lo, hi = points_xy.min(axis=0) - snap.max(), points_xy.max(axis=0) + snap.max()
    seg_lo, seg_hi = segments.min(axis=1), segments.max(axis=1)
    keep = np.all((seg_hi >= lo) & (seg_lo <= hi), axis=1)
    segments, seen_from_xy = segments[keep], seen_from_xy[keep]
    if segments.shape[0] == 0:
        return out
    dist = point_segment_distances(points_xy, segments)  # (N, M)
    near = dist < snap[:, None]
    a, along = segments[:, 0], segments[:, 1] - segments[:, 0]
    length = np.maximum(np.hypot(*along.T), 1e-12)
    past_end = np.broadcast_to(np.asarray(past_end_m, dtype=np.float64), points_xy.shape[:1])
    bounded = np.isfinite(past_end)
    runs_on = np.full((points_xy.shape[0], 1), -math.inf)
    if runs_on_m is not None and wall_runs is not None:
        runs_on = runs_on_m[:, keep] if runs_on_m.shape[1] > 1 else runs_on_m
    asked = np.isfinite(runs_on).any(axis=1)
    rows = bounded | asked
    if rows.any() and near.any():
        at = np.zeros(near.shape)  # where along each segment each vertex lies, from its start
        at[rows] = _along(points_xy[rows], a, along) / length[None]
        if bounded.any():
            past = np.maximum(-at[bounded], at[bounded] - length[None]) > 0.0
            near[bounded] &= ~past | (dist[bounded] < past_end[bounded, None])
        if asked.any() and wall_runs is not None:
            before, after = wall_runs[keep, 0], wall_runs[keep, 1]
            run_m = np.minimum(at[asked] + before[None], length[None] - at[asked] + after[None])
            near[asked] &= run_m > runs_on[asked]
    if on_shadow.any():
        normal = np.column_stack((-along[:, 1], along[:, 0])) / length[:, None]
        seen = seen_from_xy - a
        facing = np.sign(seen[:, 0] * normal[:, 0] + seen[:, 1] * normal[:, 1])  # the side its view saw
        offset = _along(points_xy[on_shadow], a, normal) * facing[None]
        near[on_shadow] &= offset >= -behind_m
    out[:, keep] = near
    return out


def _along(points_xy: FloatArray, origins_xy: FloatArray, directions_xy: FloatArray) -> FloatArray:
    """(N, M): each point's offset from each origin ((M, 2)) dotted with that origin's direction
    ((M, 2)); x and y kept apart, as :func:`~companion.core.geometry.point_segment_distances`
    does, for speed (the same bits as a sum over the axis of two)."""
    px, py = points_xy[:, 0:1], points_xy[:, 1:2]
    return np.asarray(
        (px - origins_xy[None, :, 0]) * directions_xy[None, :, 0]
        + (py - origins_xy[None, :, 1]) * directions_xy[None, :, 1],
        dtype=np.float64,
    )

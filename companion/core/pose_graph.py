"""Pose graph of keyframes joined by relative transforms (thesis 2.8.2).

Odometry edges join consecutive keyframes; loop-closure edges join two keyframes that a SLAM back
end recognised as the same place. Nothing is ever corrected in place: a loop closure only adds an
edge, and every query composes relative transforms along the graph.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from companion.core.errors import GraphError
from companion.core.geometry import FloatArray, Pose2, wrap_angle


class EdgeType(Enum):
    ODOMETRY = "odometry"
    LOOP_CLOSURE = "loop_closure"


@dataclass(frozen=True, slots=True)
class GraphEdge:
    """``from_to`` is the pose of keyframe ``to_id`` in the frame of keyframe ``from_id``."""

    from_id: int
    to_id: int
    from_to: Pose2
    kind: EdgeType


@dataclass(frozen=True, slots=True)
class Visit:
    """A keyframe reached by a breadth-first walk: hops from the start and its pose there."""

    keyframe_id: int
    hops: int
    pose_in_start: Pose2


@dataclass(frozen=True, slots=True)
class Reached:
    """Every keyframe a breadth-first walk from one keyframe reaches (itself included), as arrays
    in no particular order: ids, hops from the start, and poses in the start's frame as rows of
    ``x_m, y_m, yaw_rad``, each composed along the walk's first path (as :meth:`PoseGraph.walk`).
    Read-only: the graph hands the same arrays to every caller until the walk grows."""

    ids: NDArray[np.intp]
    hops: NDArray[np.intp]
    poses: FloatArray


@dataclass(slots=True)
class _ReachedCache:
    edges_seen: int  # how many of the graph's edges this covers
    index: dict[int, int] = field(default_factory=dict)  # keyframe id -> row
    hops: list[int] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)  # x_m, y_m, yaw_rad
    parents: list[int] = field(default_factory=list)  # row of the keyframe each was found from (-1)
    walked: int = 0  # rows below this are in the walk's queue order; later ones are leaves added
    arrays: Reached | None = None  # the walk as :class:`Reached` (read-only), until it grows
    max_hops: int | None = None  # the walk went no deeper (None: the whole graph)

    def add(self, keyframe_id: int, hops: int, pose: tuple[float, float, float], parent: int) -> None:
        self.index[keyframe_id] = len(self.hops)
        self.hops.append(hops)
        self.poses.append(pose)
        self.parents.append(parent)
        self.arrays = None

    def as_arrays(self) -> Reached:
        """The walk as :class:`Reached`, built once each time it grows."""
        if self.arrays is None:
            ids = np.fromiter(self.index, dtype=np.intp, count=len(self.index))
            hops = np.array(self.hops, dtype=np.intp)
            poses = np.array(self.poses, dtype=np.float64).reshape(-1, 3)
            for a in (ids, hops, poses):
                a.flags.writeable = False  # shared by every caller until the walk grows
            self.arrays = Reached(ids, hops, poses)
        return self.arrays


_Row = tuple[float, float, float]  # a pose as plain floats: x_m, y_m, yaw_rad


def _compose(pose: _Row, rel: Pose2) -> _Row:
    """:meth:`Pose2.compose` on plain floats (the same arithmetic, so the same bits)."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return (x + c * rel.x_m - s * rel.y_m, y + s * rel.x_m + c * rel.y_m, wrap_angle(yaw + rel.yaw_rad))


def _rows(poses: list[_Row]) -> FloatArray:
    """Poses as an (N, 3) array of ``x_m, y_m, yaw_rad``."""
    return np.array(poses, dtype=np.float64).reshape(-1, 3)


class PoseGraph:
    """Keyframe ids and the edges between them; adjacency kept both ways."""

    max_cached_walks = 256  # starts whose :meth:`reached` is kept and extended as the graph grows

    def __init__(self) -> None:
        self._adjacency: dict[int, list[tuple[int, Pose2]]] = {}
        self._edges: list[GraphEdge] = []
        self._reached: dict[int, _ReachedCache] = {}

    def __contains__(self, keyframe_id: object) -> bool:
        return keyframe_id in self._adjacency

    def __len__(self) -> int:
        return len(self._adjacency)

    @property
    def edges(self) -> tuple[GraphEdge, ...]:
        return tuple(self._edges)

    def add_keyframe(self, keyframe_id: int) -> None:
        if keyframe_id in self._adjacency:
            raise GraphError(f"keyframe {keyframe_id} already in the graph")
        self._adjacency[keyframe_id] = []

    def add_edge(self, from_id: int, to_id: int, from_to: Pose2, kind: EdgeType) -> GraphEdge:
        for k in (from_id, to_id):
            if k not in self._adjacency:
                raise GraphError(f"keyframe {k} is not in the graph")
        if from_id == to_id:
            raise GraphError("an edge must join two different keyframes")
        if not from_to.is_finite():
            raise GraphError("an edge transform must be finite")
        edge = GraphEdge(from_id, to_id, from_to, kind)
        self._edges.append(edge)
        if kind is EdgeType.LOOP_CLOSURE:
            # Walks try loop closures first: a measured relative pose, where the chain of odometry
            # edges it shortcuts carries every metre's drift.
            self._adjacency[from_id].insert(0, (to_id, from_to))
            self._adjacency[to_id].insert(0, (from_id, from_to.inverse()))
        else:
            self._adjacency[from_id].append((to_id, from_to))
            self._adjacency[to_id].append((from_id, from_to.inverse()))
        return edge

    def neighbours(self, keyframe_id: int) -> list[tuple[int, Pose2]]:
        """Directly connected keyframes with their pose in ``keyframe_id``'s frame."""
        try:
            return list(self._adjacency[keyframe_id])
        except KeyError:
            raise GraphError(f"keyframe {keyframe_id} is not in the graph") from None

    def walk(self, start_id: int, accept: Callable[[int, Pose2], bool] | None = None) -> list[Visit]:
        """Breadth-first walk by hop count from ``start_id`` (first in the list).

        A keyframe for which ``accept(id, pose_in_start)`` is False is neither visited nor
        expanded: the walk stops along that branch. Poses compose along the first path found.
        """

        def each(ids: list[int], rows: FloatArray) -> NDArray[np.bool_]:
            poses = [Pose2(*row) for row in rows.tolist()]
            return np.array([accept is None or accept(k, p) for k, p in zip(ids, poses, strict=True)], dtype=bool)

        return self.walk_levels(start_id, each)

    def walk_levels(
        self,
        start_id: int,
        accept: Callable[[list[int], FloatArray], NDArray[np.bool_]],
        bridge_hops: int = 0,
        still_m: float = 0.0,
        ahead: int = 0,
    ) -> list[Visit]:
        """:meth:`walk`, with ``accept`` asked once per hop count for every keyframe first met at
        that count (ids, and poses in the start's frame as rows of ``x_m, y_m, yaw_rad``, in the
        walk's order), so it can test them all in one vectorised pass. The walk goes on through
        up to ``bridge_hops`` refused keyframes in a row (not returned): past a turn in place,
        say, whose views look away. A refused keyframe reached by an edge shorter than
        ``still_m`` does not count towards them: a whole turn in place (ten views at one spot)
        is bridged, at any length (when the walk bridges at all: ``bridge_hops`` > 0).

        With ``ahead`` > 0, ``accept`` must judge each keyframe by its id and pose alone: each
        call then also asks about up to ``ahead`` keyframes beyond the level, walked on without
        a filter (:meth:`_judge_ahead`), and a later level takes those answers where it meets the
        keyframe at the very same pose. The same walk in a few calls instead of one per hop:
        along a chain of views most levels hold one or two keyframes, and a call's fixed cost
        was most of the walk's time. Poses compose on plain floats (:func:`_compose`, the same
        arithmetic as :meth:`Pose2.compose`): only a visit's becomes a :class:`Pose2`."""
        if start_id not in self._adjacency:
            raise GraphError(f"keyframe {start_id} is not in the graph")
        seen = {start_id}
        out = [Visit(start_id, 0, Pose2.identity())]
        # Each keyframe to go on from: its id, pose and the refused keyframes in a row up to it.
        level: list[tuple[int, _Row, int]] = [(start_id, (0.0, 0.0, 0.0), 0)]
        judged: dict[int, tuple[_Row, bool]] = {}  # asked ahead of the walk (``ahead``), at that pose
        hops = 0
        while level:
            ids: list[int] = []
            poses: list[_Row] = []
            misses: list[int] = []
            for kf_id, pose, miss in level:
                for nbr, rel in self._adjacency[kf_id]:
                    if nbr not in seen:
                        seen.add(nbr)
                        ids.append(nbr)
                        poses.append(_compose(pose, rel))
                        moved = still_m <= 0.0 or bridge_hops == 0 or math.hypot(rel.x_m, rel.y_m) >= still_m
                        misses.append(miss + 1 if moved else miss)
            hops += 1
            if not ids:
                ok: list[bool] = []
            elif ahead > 0:
                ok = self._judge_ahead(ids, poses, accept, judged, seen, ahead)
            else:
                ok = accept(ids, _rows(poses)).tolist()
            level = []
            for k, pose, keep, miss in zip(ids, poses, ok, misses, strict=True):
                if keep:
                    out.append(Visit(k, hops, Pose2(*pose)))
                    level.append((k, pose, 0))
                elif miss <= bridge_hops:
                    level.append((k, pose, miss))
        return out

    def _judge_ahead(
        self,
        ids: list[int],
        poses: list[_Row],
        accept: Callable[[list[int], FloatArray], NDArray[np.bool_]],
        judged: dict[int, tuple[_Row, bool]],
        seen: set[int],
        ahead: int,
    ) -> list[bool]:
        """``accept`` for one level of :meth:`walk_levels`: answers ``judged`` holds for a
        keyframe at that very pose, and one call for the rest together with up to ``ahead``
        keyframes beyond them (breadth first from them, poses composed as the walk composes them,
        none the walk has met), whose answers go into ``judged`` for the levels to come."""
        todo = [i for i, (k, pose) in enumerate(zip(ids, poses, strict=True)) if judged.get(k, (None,))[0] != pose]
        if todo:
            ask_ids, ask_poses = [ids[i] for i in todo], [poses[i] for i in todo]
            met = set(ask_ids)
            queue = deque(zip(ask_ids, ask_poses, strict=True))
            extra = 0
            while queue and extra < ahead:
                k, pose = queue.popleft()
                for nbr, rel in self._adjacency[k]:
                    if nbr in seen or nbr in met or extra >= ahead:
                        continue
                    met.add(nbr)
                    nbr_pose = _compose(pose, rel)
                    ask_ids.append(nbr)
                    ask_poses.append(nbr_pose)
                    queue.append((nbr, nbr_pose))
                    extra += 1
            answers = accept(ask_ids, _rows(ask_poses))
            for k, pose, ok in zip(ask_ids, ask_poses, answers.tolist(), strict=True):
                judged[k] = (pose, bool(ok))
        return [judged[k][1] for k in ids]

    def order_from(self, start_id: int) -> list[int]:
        """Every keyframe connected to ``start_id``, nearest (in hops) first, in :meth:`walk`'s
        order, without composing a pose for each."""
        if start_id not in self._adjacency:
            raise GraphError(f"keyframe {start_id} is not in the graph")
        order, seen = [start_id], {start_id}
        for kf_id in order:  # grows as the walk goes: a breadth-first queue
            for nbr, _ in self._adjacency[kf_id]:
                if nbr not in seen:
                    seen.add(nbr)
                    order.append(nbr)
        return order

    def reached(self, start_id: int, max_hops: int | None = None) -> Reached:
        """What :meth:`walk` from ``start_id`` reaches, as arrays: every keyframe within
        ``max_hops`` (None: the whole graph), and maybe some farther, which callers filter out.
        The walk stops there: most callers trust no chain longer than the drift margin, and a
        whole walk of a large graph costs a millisecond or more (after a loop closure, afresh
        from every keyframe asked about). Kept per start, and extended (not walked again) while
        the graph only grows by new keyframes hung on by one edge: a leaf moves no one's first
        path, so its hops and pose follow from its parent's. Any other edge (a loop closure)
        makes the next call walk afresh, as does a call that asks deeper than the cached walk."""
        cache = self._reached.pop(start_id, None)
        deep_enough = cache is not None and (
            cache.max_hops is None or (max_hops is not None and max_hops <= cache.max_hops)
        )
        if cache is None or not deep_enough or not self._extend(cache):
            cache = self._walk_all(start_id, max_hops)
        self._reached[start_id] = cache  # newest last: the oldest go first
        while len(self._reached) > self.max_cached_walks:
            del self._reached[next(iter(self._reached))]
        return cache.as_arrays()

    def _walk_all(self, start_id: int, max_hops: int | None = None) -> _ReachedCache:
        """:meth:`walk` without a filter, on plain floats (no object per keyframe): the same
        arithmetic as :meth:`Pose2.compose`, so the same poses to the last bit, several times
        faster. Every loop closure makes the planner's graph checks walk afresh. Keyframes
        ``max_hops`` away end the walk (not expanded): a breadth-first walk meets every one
        nearer first, by the same first paths as a whole walk."""
        if start_id not in self._adjacency:
            raise GraphError(f"keyframe {start_id} is not in the graph")
        cache = _ReachedCache(len(self._edges), max_hops=max_hops)
        cache.add(start_id, 0, (0.0, 0.0, 0.0), -1)
        index, hops, poses, parents, adjacency = cache.index, cache.hops, cache.poses, cache.parents, self._adjacency
        order = [start_id]
        cos, sin, pi, tau = math.cos, math.sin, math.pi, 2.0 * math.pi
        last = math.inf if max_hops is None else max_hops
        for row, kf_id in enumerate(order):  # grows as the walk goes: a breadth-first queue
            if hops[row] >= last:
                break  # the queue holds only keyframes this far on from here
            x, y, yaw = poses[row]
            c, s = cos(yaw), sin(yaw)
            h = hops[row] + 1
            for nbr, rel in adjacency[kf_id]:
                if nbr in index:
                    continue
                index[nbr] = len(order)
                order.append(nbr)
                hops.append(h)
                parents.append(row)
                rx, ry = rel.x_m, rel.y_m
                poses.append((x + c * rx - s * ry, y + s * rx + c * ry, (yaw + rel.yaw_rad + pi) % tau - pi))
        cache.walked = len(order)
        return cache

    def _extend(self, cache: _ReachedCache) -> bool:
        """Add the leaves hung on since ``cache`` was made, and pass over edges that change no
        first path; False when an edge did more."""
        for edge in self._edges[cache.edges_seen :]:
            a_in, b_in = edge.from_id in cache.index, edge.to_id in cache.index
            if a_in == b_in:
                if a_in and not _keeps_walk(cache, cache.index[edge.from_id], cache.index[edge.to_id]):
                    return False  # joins two reached keyframes: first paths may change
                continue  # joins two unreached ones: judged when an edge reaches them
            parent, leaf, rel = (
                (edge.from_id, edge.to_id, edge.from_to) if a_in else (edge.to_id, edge.from_id, edge.from_to.inverse())
            )
            if len(self._adjacency[leaf]) != 1:
                return False  # not a leaf: it may bring others along
            row = cache.index[parent]
            if cache.max_hops is not None and cache.hops[row] >= cache.max_hops:
                continue  # past the walk's depth: left out, as the walk leaves it
            leaf_pose = Pose2(*cache.poses[row]).compose(rel)
            cache.add(leaf, cache.hops[row] + 1, (leaf_pose.x_m, leaf_pose.y_m, leaf_pose.yaw_rad), row)
        cache.edges_seen = len(self._edges)
        return True

    def path(self, from_id: int, to_id: int, avoid: Collection[tuple[int, int]] = ()) -> list[int]:
        """Fewest-hop path of keyframe ids from ``from_id`` to ``to_id`` (both included), not
        using the edges listed in ``avoid`` (as ``(a, b)`` pairs, either direction)."""
        if to_id not in self._adjacency or from_id not in self._adjacency:
            raise GraphError(f"keyframe {from_id} or {to_id} is not in the graph")
        parent: dict[int, int] = {from_id: from_id}
        queue: deque[int] = deque([from_id])
        while queue:
            k = queue.popleft()
            if k == to_id:
                break
            for nbr, _ in self._adjacency[k]:
                if nbr not in parent and (k, nbr) not in avoid and (nbr, k) not in avoid:
                    parent[nbr] = k
                    queue.append(nbr)
        if to_id not in parent:
            raise GraphError(f"keyframe {to_id} is not connected to {from_id}")
        out = [to_id]
        while out[-1] != from_id:
            out.append(parent[out[-1]])
        return out[::-1]

    def relative(self, from_id: int, to_id: int) -> Pose2:
        """Pose of ``to_id`` in ``from_id``'s frame, composed along the fewest-hop path."""
        ids = self.path(from_id, to_id)
        pose = Pose2.identity()
        for a, b in itertools.pairwise(ids):
            pose = pose.compose(self._edge_between(a, b))
        return pose

    def _edge_between(self, a: int, b: int) -> Pose2:
        for nbr, rel in self._adjacency[a]:
            if nbr == b:
                return rel
        raise GraphError(f"no edge between {a} and {b}")


def _keeps_walk(cache: _ReachedCache, row_a: int, row_b: int) -> bool:
    """Whether a new edge between two reached keyframes (rows of ``cache``) leaves the walk as it
    is: when the walk takes either end from its queue, the other is found already, so the edge
    is passed over, wherever it sits in their adjacency. So it is when both are as many hops
    away (every keyframe of a hop count is found before the first of them is taken), or one hop
    apart with the farther one found from a keyframe taken before the nearer one (in the walk's
    queue order, which leaves added since do not have). A loop closure in a place the graph
    already joins tightly is often so; the others make the next call walk afresh."""
    hops_a, hops_b = cache.hops[row_a], cache.hops[row_b]
    if hops_a == hops_b:
        return True
    if abs(hops_a - hops_b) != 1:
        return False
    near, far = (row_a, row_b) if hops_a < hops_b else (row_b, row_a)
    return cache.parents[far] < near < cache.walked

"""Loop closures found by the companion itself: a new keyframe's view matched to an old one's.

Without a SLAM back end (MAVLink carries no loop closures) the pose graph is one chain of
odometry edges, and a place flown back to after many keyframes sits where the drift since puts
it. Here a new keyframe is matched (:mod:`companion.core.scan_matching`) against the old
keyframes the graph places near it and facing its way, far from it along the graph; the first
trustworthy match becomes a loop-closure edge, the same as a back end's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from companion.core.geometry import FloatArray, Pose2, wrap_angles
from companion.core.local_map import Keyframe, LocalMap
from companion.core.scan_matching import (
    ScanMatch,
    ScanMatchParams,
    accept_match,
    enough_pairs,
    match_to_walls,
    view_points,
)


@dataclass(frozen=True, slots=True)
class LoopClosingParams:
    """Tuning for the companion's own loop closures (off unless ``enabled``)."""

    enabled: bool = False
    min_hops: int = 8  # nearer along the graph, the odometry between the two views is good enough
    max_distance_m: float = 3.0  # between the two views' origins, as the graph places them
    max_yaw_difference_rad: float = 1.0  # a 90-degree view shares little with one facing farther away
    max_candidates: int = 3  # matches tried per new keyframe, nearest first (one per step)
    # A match may move the new view this far from where the graph put it, plus this much per
    # hop between the two: the odometry's drift along the graph, at most (a larger jump is more
    # likely a similar-looking other place). Per hop, the same as the map's drift margin.
    max_correction_m: float = 0.5
    max_correction_per_hop_m: float = 0.05
    max_correction_rad: float = 0.35
    point_spacing_m: float = 0.15  # the new view's walls are matched as points this far apart
    # The ambiguity test's restarts: the match's pose shifted this far along and across its
    # walls, and turned this far (see ViewMatcher).
    ambiguity_shift_m: float = 0.7
    ambiguity_turn_rad: float = 0.25
    same_pose_m: float = 0.1  # a restart that comes back this near (and turned this little) agrees
    same_pose_rad: float = 0.03
    match: ScanMatchParams = field(default_factory=ScanMatchParams)


@dataclass(frozen=True, slots=True)
class FoundClosure:
    """A loop closure: ``later_id``'s pose in ``earlier_id``'s frame, as the views' match put it."""

    earlier_id: int
    later_id: int
    earlier_to_later: Pose2
    match: ScanMatch


@dataclass(frozen=True, slots=True)
class Candidate:
    """An old keyframe to match a new one to: the new one's pose in its frame as the graph
    puts it (the match's first guess), and the hops between them."""

    old_id: int
    guess: Pose2
    hops: int


def loop_closure_candidates(
    local_map: LocalMap, keyframe_id: int, params: LoopClosingParams, source_xy: FloatArray | None = None
) -> list[Candidate]:
    """The old keyframes worth matching keyframe ``keyframe_id``'s view to, nearest first: far
    along the graph, near it and facing its way as the graph places them, with walls to match.
    Given the new view's points (``source_xy``, its frame), only views with enough walls near
    them as the graph places the two: a match pairs only points within its first gate of a wall,
    and needs ``min_inliers`` of them from the start (most views near a revisit share no wall:
    a 90-degree view of a room sees little of it)."""
    new = local_map.keyframes[keyframe_id]
    if new.walls.shape[0] == 0:
        return []
    reached = local_map.graph.reached(keyframe_id)
    x, y, yaw = reached.poses[:, 0], reached.poses[:, 1], reached.poses[:, 2]
    dist = np.hypot(x, y)
    near = (
        (reached.hops >= params.min_hops)
        & (dist <= params.max_distance_m)
        & (np.abs(wrap_angles(yaw)) <= params.max_yaw_difference_rad)
    )
    out: list[Candidate] = []
    for row in np.flatnonzero(near)[np.argsort(dist[near], kind="stable")]:
        old_id = int(reached.ids[row])
        if local_map.keyframes[old_id].walls.shape[0] == 0:
            continue
        old_in_new = Pose2(float(x[row]), float(y[row]), float(yaw[row]))
        guess = old_in_new.inverse()
        if source_xy is not None and not enough_pairs(
            source_xy, local_map.keyframes[old_id].walls, guess, params.match
        ):
            continue
        out.append(Candidate(old_id, guess, int(reached.hops[row])))
        if len(out) == params.max_candidates:
            break
    return out


class ViewMatcher:
    """Finds a loop closure for the newest keyframe, a little work per :meth:`step`: its
    candidates, then one match per step, then the winner's ambiguity test, one restart per step.

    A match is taken only if it is unique: matched again from guesses shifted (along and across
    its walls, and turned) it either fails or comes back to the same pose. A view that fits as
    well a door's width along a wall is a repeated structure, not a place recognised, and a
    false loop closure misplaces every guess made through it afterwards."""

    def __init__(self, params: LoopClosingParams) -> None:
        self.params = params
        self._keyframe_id: int | None = None
        self._next_id: int | None = None  # the newest keyframe waiting for the search going on
        self._source: FloatArray = np.zeros((0, 2))
        self._candidates: list[Candidate] | None = None
        self._found: FoundClosure | None = None  # the match under test
        self._restarts: list[Pose2] = []

    @property
    def busy(self) -> bool:
        return self._keyframe_id is not None

    def start(self, keyframe_id: int) -> None:
        """Look for a loop closure for this (new) keyframe, dropping the search going on unless
        a match found is under its ambiguity test: that one ends first, the newest keyframe
        waiting (only the newest: a keyframe it replaces is not searched for). A search spans a
        few steps and a keyframe comes every few steps when flying: dropped mid-test, two of
        every three matches found were lost."""
        if self._found is not None:
            self._next_id = keyframe_id
            return
        self._begin(keyframe_id)

    def _begin(self, keyframe_id: int | None) -> None:
        self._keyframe_id = keyframe_id
        self._next_id = None
        self._candidates = None
        self._found = None
        self._restarts = []

    def step(self, local_map: LocalMap) -> FoundClosure | None:
        """One piece of the search; the loop closure once one has passed every test."""
        kf_id = self._keyframe_id
        if kf_id is None:
            return None
        p = self.params
        if self._candidates is None:
            self._source = _view_points(local_map.keyframes[kf_id], p.point_spacing_m)
            self._candidates = loop_closure_candidates(local_map, kf_id, p, self._source)
            return None
        if self._found is not None:
            return self._restart(local_map)
        if not self._candidates:
            self._begin(self._next_id)
            return None
        candidate = self._candidates.pop(0)
        found = self._match(local_map, candidate, candidate.guess)
        if found is not None and _within_drift(candidate, found.earlier_to_later, p):
            self._found = found
            self._restarts = _restart_guesses(found, p.ambiguity_shift_m, p.ambiguity_turn_rad)
            self._restarts.append(candidate.guess)  # the last, with a narrow gate (see _restart)
        return None

    def _restart(self, local_map: LocalMap) -> FoundClosure | None:
        found = self._found
        assert found is not None
        guess = self._restarts.pop(0)
        candidate = Candidate(found.earlier_id, guess, 0)
        # From the graph's own guess, pairing only returns near the walls they fit there: if the
        # views fit as well close to where odometry puts them, the farther match is not unique.
        narrow = None if self._restarts else replace(self.params.match, start_gate_m=self.params.match.final_gate_m)
        other = self._match(local_map, candidate, guess, narrow)
        if other is not None and not _same_pose(other.earlier_to_later, found.earlier_to_later, self.params):
            self._found = None  # ambiguous: on to the next candidate
            return None
        if self._restarts:
            return None
        self._begin(self._next_id)
        return found

    def _match(
        self, local_map: LocalMap, candidate: Candidate, guess: Pose2, match_params: ScanMatchParams | None = None
    ) -> FoundClosure | None:
        assert self._keyframe_id is not None
        p = self.params
        new = local_map.keyframes[self._keyframe_id]
        old = local_map.keyframes[candidate.old_id]
        aligned = match_to_walls(self._source, old.walls, guess, match_params or p.match)
        if aligned is None:
            return None
        target = _view_points(old, p.point_spacing_m)
        match = accept_match(self._source, new.polygon.shape, target, old.polygon.shape, aligned, p.match)
        if match is None:
            return None
        return FoundClosure(candidate.old_id, self._keyframe_id, match.pose, match)


def _within_drift(candidate: Candidate, pose: Pose2, params: LoopClosingParams) -> bool:
    """Whether the match moved the new view no farther from the graph's guess than the
    odometry can have drifted between the two views."""
    moved = candidate.guess.between(pose)
    allowed_m = params.max_correction_m + params.max_correction_per_hop_m * candidate.hops
    return math.hypot(moved.x_m, moved.y_m) <= allowed_m and abs(moved.yaw_rad) <= params.max_correction_rad


def _restart_guesses(found: FoundClosure, shift_m: float, turn_rad: float) -> list[Pose2]:
    """The match's pose shifted both ways along its walls' weakest and strongest directions,
    and turned both ways: the guesses its ambiguity test starts from."""
    pose = found.earlier_to_later
    wx, wy = found.match.weak_axis
    out = []
    for dx, dy in ((wx, wy), (-wy, wx)):
        for sign in (1.0, -1.0):
            out.append(Pose2(pose.x_m + sign * shift_m * dx, pose.y_m + sign * shift_m * dy, pose.yaw_rad))
    out += [Pose2(pose.x_m, pose.y_m, pose.yaw_rad + turn_rad), Pose2(pose.x_m, pose.y_m, pose.yaw_rad - turn_rad)]
    return out


def _same_pose(a: Pose2, b: Pose2, params: LoopClosingParams) -> bool:
    rel = a.between(b)
    return math.hypot(rel.x_m, rel.y_m) <= params.same_pose_m and abs(rel.yaw_rad) <= params.same_pose_rad


def _view_points(kf: Keyframe, spacing_m: float) -> FloatArray:
    """The keyframe's walls and obstacle vertices as points, in its frame (:func:`view_points`)."""
    return view_points(kf.polygon, kf.walls, spacing_m)

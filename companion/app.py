"""``companion run``: build the links the config names, run the service, write the report.

This is the only place that picks transports; the service sees the interfaces of
:mod:`companion.links.base` only.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

from companion.config import Config
from companion.core.explorer import ExplorerParams
from companion.core.local_map import MapParams
from companion.core.loop_closing import LoopClosingParams
from companion.core.planner import PlannerParams
from companion.errors import CompanionError
from companion.links.base import FlightControl, InputSource
from companion.service import Service, ServiceSettings

log = logging.getLogger("companion")

EXIT_OK, EXIT_FAILED = 0, 1
NORMAL_ENDINGS = ("complete", "unreachable_frontiers_left")


async def run_service(config: Config, report_path: Path | None) -> int:
    """Connect, fly one exploration, land; 0 when the exploration ended normally."""
    from companion.links.mavlink_link import MavlinkLink, MavlinkSettings

    v = config.vehicle
    link = MavlinkLink(
        MavlinkSettings(
            v.mavlink,
            baud=v.baud,
            setpoint_rate_hz=v.setpoint_rate_hz,
            altitude_m=v.altitude_m,
            command_timeout_s=v.command_timeout_s,
            arm_timeout_s=v.arm_timeout_s,
            input_rate_hz=v.input_rate_hz,
        )
    )
    closers: list[Any] = [link]
    report: dict[str, Any] = {}
    try:
        await link.connect()
        control: FlightControl = link
        if v.control == "mavsdk":
            from companion.links.mavsdk_control import MavsdkControl

            assert v.mavsdk_url is not None
            mavsdk = MavsdkControl(v.mavsdk_url, v.altitude_m)
            closers.append(mavsdk)
            await mavsdk.connect()
            control = mavsdk
        inputs: list[InputSource] = []
        if config.inputs.odometry == "mavlink" or config.inputs.scan == "mavlink":
            inputs.append(_MavlinkInputs(link, config))
        outputs = None
        drops = None
        if config.zenoh is not None:
            from companion.links.zenoh_keys import Keys
            from companion.links.zenoh_link import ZenohInputs, ZenohOutputs, ZenohSettings, open_session

            z = config.zenoh
            settings = ZenohSettings(z.mode, tuple(z.connect), tuple(z.listen), z.multicast_scouting, dict(z.overrides))
            session = await asyncio.to_thread(open_session, settings)  # zenoh.open blocks
            closers.insert(0, _SessionCloser(session))
            keys = Keys(z.prefix, z.vehicle)
            i = config.inputs
            streams = {
                n
                for n, src in (("odometry", i.odometry), ("scan", i.scan), ("loop_closure", i.loop_closure))
                if src == "zenoh"
            }
            if streams:
                zin = ZenohInputs(session, keys, streams)
                closers.append(zin)
                inputs.append(zin)
                drops = zin.drops
            outputs = ZenohOutputs(session, keys)
            closers.append(outputs)
        service = Service(
            ServiceSettings(
                altitude_m=v.altitude_m,
                input_timeout_s=config.safety.input_timeout_s,
                startup_timeout_s=config.safety.startup_timeout_s,
                max_time_s=config.exploration.max_time_s,
                on_stop=config.safety.on_stop,
            ),
            inputs,
            control,
            explorer_params=explorer_params(config),
            on_status=None if outputs is None else _publisher(outputs, drops),
        )
        task = asyncio.create_task(service.run())
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, task.cancel)
        try:
            report = await task
        except asyncio.CancelledError:
            report = service.report()
        finally:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(sig)
        for source in inputs:
            drops = getattr(source, "drops", None)
            if drops is not None:
                report["inputs"]["rejected"].update(drops.counts)
    except CompanionError as err:
        log.error("%s", err)
        report = {"termination": "error", "reason": str(err)}
    finally:
        for closer in reversed(closers):
            await closer.close()
    if report_path is not None:
        try:  # checked before the flight (cli); a disk that filled since is logged, not a traceback
            report_path.parent.mkdir(parents=True, exist_ok=True)
            report_path.write_text(json.dumps(report, indent=2) + "\n")
        except OSError as exc:
            log.error("cannot write the report %s: %s", report_path, exc.strerror or exc)
    log.info("exploration ended: %s", report.get("termination"))
    return EXIT_OK if report.get("termination") in NORMAL_ENDINGS else EXIT_FAILED


class _MavlinkInputs:
    """The MAVLink link as an input source, passing on only the streams the config takes from it."""

    def __init__(self, link: Any, config: Config) -> None:
        self._link = link
        self._config = config

    def subscribe(self, on_odometry: Any = None, on_scan: Any = None, on_loop_closure: Any = None) -> None:
        i = self._config.inputs
        self._link.subscribe(
            on_odometry if i.odometry == "mavlink" else None,
            on_scan if i.scan == "mavlink" else None,
        )


class _SessionCloser:
    def __init__(self, session: Any) -> None:
        self._session = session

    async def close(self) -> None:
        await asyncio.to_thread(self._session.close)


def _publisher(outputs: Any, drops: Any) -> Any:
    def publish(service: Service) -> None:
        h = service.health
        health = {
            "state": h.state.value,
            "odometry_count": h.odometry_count,
            "scan_count": h.scan_count,
            "loop_closure_count": h.loop_closure_count,
            "scans_ahead_of_odometry": h.scans_ahead_of_odometry,
            "rejected": {**h.rejected, **(drops.counts if drops is not None else {})},
            "step_ms_last": round(service.step_ms[-1], 3) if service.step_ms else None,
        }
        outputs.update(h.state.value, h.reason, health, service.explorer.map, service.setpoint)

    return publish


def map_params(with_loop_closures: bool, drift_m_per_keyframe: float) -> MapParams:
    """The map's tuning for the inputs: without a loop-closure source, new views are closed
    against every view along the pose graph (see MapParams.close_new_through_graph), as deep
    inside it as the odometry's drift per keyframe requires, and the neighbourhood walk bridges
    no views that do not overlap (bridging them there, six maps with perfect odometry ended 14
    of 18 runs `complete` against 18, lshape seed 3 at coverage 0.64; not yet understood).
    (`companion sim` asks it too.)"""
    if with_loop_closures:
        return MapParams(chain_margin_per_hop_m=drift_m_per_keyframe)
    return MapParams(
        close_new_through_graph=True, chain_margin_per_hop_m=drift_m_per_keyframe, neighbourhood_bridge_hops=0
    )


def planner_params(with_loop_closures: bool) -> PlannerParams:
    """The planner's tuning for the inputs: without a loop-closure source, goals are scored with
    session 22's lighter distance weight (0.08 rad per metre). The 0.2 that shortened runs with
    closures by a tenth ended 2 of 18 runs without them short (six maps, seeds 1-3, perfect
    odometry; lshape 2 at its 900 s limit): flying back past a place, each new view there offered
    the same nearby frontier again, and the vehicle went to it and back for ever (0.12 and 0.15
    ended 1 and 4 runs short; 0.08 none, and 12 % sooner than session 22 with the wider turn).
    Session 46's two changes, measured with closures only, stay off: the vehicle turns to look
    on arriving at a goal (``look_ahead_m`` 0; on the last metre, the room run without closures,
    seed 1, went to its 900 s limit where it had ended by itself at 594 s), and a goal path's
    leg the scan sees grazing a return drops the goal (``sidestep_goal_legs``; flown round, the
    loop run with the companion's own closures, seed 2, ended at coverage 0.947). Nor is session
    48's shorter settle at a goal: 1 s, as before. Nor session 50's longer run a frontier needs
    while longer ones are left (``min_frontier_size_m`` 0.6): without closures, 0.3 m as before."""
    if with_loop_closures:
        return PlannerParams()
    return PlannerParams(
        distance_weight_rad_per_m=0.08,
        look_ahead_m=0.0,
        sidestep_goal_legs=False,
        settle_s=1.0,
        min_frontier_size_m=0.3,
    )


LoopClosureSource = Literal["back_end", "scan_matching", "none"]


def tuning_for(
    loop_closures: LoopClosureSource, drift_m_per_keyframe: float, drift_sigma_m_per_sqrt_m: float | None = None
) -> ExplorerParams:
    """The explorer's tuning for where loop closures come from: ``back_end`` (a SLAM back end:
    Zenoh, or the simulator's), ``scan_matching`` (the companion matches its own views, see
    companion.core.loop_closing) or ``none``; and for how far the odometry drifts
    (``drift_sigma_m_per_sqrt_m``, one sigma per axis after a metre: the remembered returns'
    alignment weighs it as its prior, and what the alignment leaves unknown widens the berth the
    lead keeps from them; None: ``MemoryAlignParams``' own, the thesis's drift; the heading's
    share as there).

    Matched closures are sparse (a 90-degree view matches only views that face its way), so the
    map and planner keep the tuning for no closures, and flying back the vehicle takes a view
    every metre as when exploring: each is a chance to recognise where it is (six maps with the
    thesis's drift, seeds 1-3, while tuning: every 3 m, 7 of 18 runs ended below coverage 0.99;
    every metre, 2).

    Odometry edges are matched (see companion.core.odometry_matching) with a back end and with
    own loop closures, not with none. With the simulated back end it saved 4 % of the
    exploration time on 22 maps, seeds 1-10 (session 27). With own loop closures it lowers the
    drift the matcher must bridge (six maps, seeds 1-5, thesis drift: mean coverage 0.937 ->
    0.992, the worst run 0.41 -> 0.93); with a match under its ambiguity test no longer dropped
    for each new keyframe (companion.core.loop_closing.ViewMatcher.start) as well, twice the
    loop closures, and seeds 1-10 reached coverage 0.99 in 53 runs of 60 against 46 (55 with
    the candidates that cannot match passed over; docs/benchmarks.md, session 62). With none,
    not measured since session 27.

    The setpoint lead checks the way momentum takes the vehicle (companion.core.setpoint_lead)
    only with a back end too: there it saved 4.6 % of the exploration time (22 maps, seeds 1-5);
    with own loop closures it saved 11 % but reached coverage 0.99 in 22 of 30 runs against 25
    (office 2 of 5 against 5; session 28, docs/benchmarks.md), so that mode keeps the check
    along the motion's straight line.

    The estimator's velocity (when the odometry carries one) is taken only with a back end too:
    there it saved 1.5 % of the time (22 maps, seeds 1-10); with own loop closures, six maps,
    seeds 1-5, one run crashed (lshape 5) and loop seed 2 stopped at coverage 0.86 (session 37).

    So is the remembered returns' margin at the field of view's edge
    (``ExplorerParams.obstacle_memory_margin_m``): with a back end it cost about 1 % of the
    time (22 maps, seeds 1-10) and keeps a wall's end beside the vehicle remembered; with own
    loop closures (six maps, seeds 1-5) 21 runs of 30 reached coverage 0.99 against 24, one
    stopping at 0.37 (session 41).

    So is aligning the remembered returns to each new scan, with the berth that grows with what
    the alignments could not fix (``ExplorerParams.obstacle_memory_align``, session 48): with own
    loop closures, loop seed 2 no longer finished (frontiers left at coverage 1.000 after 900 s).
    Session 62 measured these four together in that mode (the predicted way, the margin, the
    alignment, the velocity; odometry edges matched): 20 runs of 30 reached coverage 0.99
    against 23 without them, the worst 0.607 against 0.933."""
    if loop_closures not in ("back_end", "scan_matching", "none"):
        raise ValueError(f"unknown loop-closure source {loop_closures!r}")
    back_end = loop_closures == "back_end"
    params = ExplorerParams(map=map_params(back_end, drift_m_per_keyframe), planner=planner_params(back_end))
    if drift_sigma_m_per_sqrt_m is not None:
        drift = params.obstacle_memory_align
        scale = drift_sigma_m_per_sqrt_m / drift.drift_xy_m_per_sqrt_m  # the thesis's: 1
        params = replace(
            params,
            obstacle_memory_align=replace(
                drift,
                drift_xy_m_per_sqrt_m=drift_sigma_m_per_sqrt_m,
                drift_yaw_rad_per_sqrt_m=drift.drift_yaw_rad_per_sqrt_m * scale,  # the heading's share kept
            ),
        )
    if not back_end:
        params = replace(
            params,
            odometry_matching=replace(params.odometry_matching, enabled=loop_closures == "scan_matching"),
            lead=replace(params.lead, predict_way=False, look_follow_m=0.0),  # an unaligned memory stays put
            use_reported_velocity=False,
            obstacle_memory_margin_m=0.0,
            obstacle_memory_align=replace(params.obstacle_memory_align, enabled=False),
        )
    if loop_closures == "scan_matching":
        params = replace(
            params,
            loop_closing=LoopClosingParams(enabled=True, max_correction_per_hop_m=drift_m_per_keyframe),
            backtrack_keyframe_distance_m=params.keyframe_distance_m,
        )
    return params


def explorer_params(config: Config) -> ExplorerParams:
    """The tuning a config implies (see :func:`tuning_for`); the setpoint lead bounds the speed."""
    source: LoopClosureSource = "back_end" if config.inputs.loop_closure == "zenoh" else config.inputs.loop_closure
    exploration = config.exploration
    params = tuning_for(
        source, exploration.odometry_drift_m_per_keyframe, exploration.odometry_drift_sigma_m_per_sqrt_m
    )
    lead = replace(
        params.lead, max_lead_m=config.vehicle.max_setpoint_lead_m, model_accel_mps2=config.vehicle.braking_accel_mps2
    )
    params = replace(params, lead=lead, max_scan_range_m=exploration.max_scan_range_m)
    if config.exploration.match_odometry_edges is not None:
        params = replace(
            params, odometry_matching=replace(params.odometry_matching, enabled=config.exploration.match_odometry_edges)
        )
    return params

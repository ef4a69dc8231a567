"""The blind robot's parts, made from its parameters and what it may know of the world file.

:func:`assemble` sizes the robot, and builds its perception, the floor it asked about, its regions
of interest, its map, its way of giving way and its controller's settings from ``~params``; the
node (drvs/ros/robot.py) only wires them to ROS. What each parameter means: docs/nodes/blind_robot.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drvs.robot.asked import AskedFloor
from drvs.robot.controller import ControllerSettings
from drvs.robot.mapping import MapBuilder
from drvs.robot.mission import fused_role, obstacle_memory_ttl
from drvs.robot.params import WATCH, RobotParams
from drvs.robot.perception import Perception, RegionPolicy
from drvs.robot.traffic import YIELD_MARGIN, Yielding
from drvs.sim.world import FleetRobot, World

__all__ = ['RobotParts', 'assemble']


@dataclass
class RobotParts:
    """What :func:`assemble` makes."""

    floor_size: tuple[float, float]
    speed: float
    robot_radius: float  # the circle that holds the body whatever its heading
    watching: bool  # standing requests (~requests watch), else polling
    fused_roles: list[str]  # the roles asked for fused answers
    perception: Perception
    asked: AskedFloor
    regions: RegionPolicy
    map: MapBuilder
    yielding: Yielding
    settings: ControllerSettings


def assemble(params: RobotParams, world: World, me: FleetRobot, name: str) -> RobotParts:
    """The parts of robot ``me`` of ``world`` (only its colour models, the floor, its size and
    speed), for the node ``name`` (its watch ids' prefix)."""
    speed = params.speed or me.body.speed
    size = me.body.size
    radius = params.robot_radius if params.robot_radius is not None else math.hypot(size[0], size[1]) / 2
    fused = [role for role in me.colour_models if fused_role(params, role)]
    perception = Perception(me.colour_models, name, watch_keep=params.watch_duration, fused=fused)
    roles = perception.obstacle_roles
    # Patience differs between the robots of a fleet, so two giving way to each other do not wait for ever.
    rank = sorted(robot.name for robot in world.robots).index(me.name)
    return RobotParts(
        floor_size=world.floor_size,
        speed=speed,
        robot_radius=radius,
        watching=params.requests == WATCH,
        fused_roles=fused,
        perception=perception,
        asked=AskedFloor(roles, params.answer_wait),
        regions=RegionPolicy(
            world.floor_size, roles, radius, params.self_margin, params.roi_margin, params.fix_timeout
        ),
        map=MapBuilder(
            world.floor_size,
            (size[0], size[1]),
            radius,
            roles,
            ttl=obstacle_memory_ttl(params),
            # A watch's "all gone" keeps the outlines ~obstacle_ttl more, as polling would.
            linger=params.obstacle_ttl,
            map_period=params.map_period,
            resolution=params.resolution,
            clearance=params.robot_clearance,
            horizon=params.traffic_horizon,
            fused=fused,
            caution=params.obstacle_clearance,
            cut_roles=perception.cut_roles,
            robot_height=params.robot_height if params.robot_height is not None else size[2],
        ),
        yielding=Yielding(
            params.traffic_horizon,
            distance=2 * radius + YIELD_MARGIN,
            patience=params.yield_patience * (1 + rank / 2),
        ),
        settings=ControllerSettings(
            speed=speed,
            goal_tolerance=params.goal_tolerance,
            fix_timeout=params.fix_timeout,
            unreachable_timeout=params.unreachable_timeout,
            lookahead=params.lookahead,
            replan_distance=params.replan_distance,
            route_tolerance=params.route_tolerance,
            corridor_margin=params.roi_margin / 2,
            radius=radius,
            people_horizon=params.people_horizon,
        ),
    )

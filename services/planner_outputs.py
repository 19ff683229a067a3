"""The planner service's outputs: each plan's command and `Plan` message (`plan_message`), the task and its grid, and
the nominal plan as a ROS 2 nav_msgs/Path (`Ros2PlanPublisher`); `Outputs` publishes them (`services/planner.py`)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Protocol

import numpy as np
from pydantic import Field

from schemas import Command, DecodeError, OccupancyGrid, Plan, State
from services.codec.convert import costmap_to_message
from services.codec.ros2_topic import Ros2Topic
from services.runtime.node import Node
from services.runtime.scheduling import process_age_s

if TYPE_CHECKING:
    from gpmppi.mppi.cycle import Planned
    from gpmppi.mppi.planner import PlanResult
    from gpmppi.tasks import Task


class Ros2PlanOutput(Ros2Topic):
    """The nominal plan as a ROS 2 nav_msgs/Path (what a Nav2 controller publishes as its local plan)."""

    enabled: bool = Field(False, description="publish each Plan's nominal trajectory as nav_msgs/Path CDR")
    topic: str = Field("local_plan", description="ROS 2 topic (relative to namespace)")
    gid_seed: int | None = Field(None, description="seed of the rmw_zenoh source gid (None: random)")



class PlanOutputSettings(Protocol):
    """What `Outputs` reads of the planner service's settings."""

    plan_every: int  # publish every n-th plan
    plan_samples: int  # rollouts per Plan message
    ros2_plan: Ros2PlanOutput


def plan_message(
    result: PlanResult, stamp_ns: int, task: Task, n_samples: int,
    extra_timings_ms: dict[str, float] | None = None, weights_stale: bool = False,
) -> Plan:
    from gpmppi.mppi.task_kinds import kind_class_for

    covs = np.asarray(result.covariances)
    cov_xy = np.stack([covs[:, 0, 0], covs[:, 0, 1], covs[:, 1, 1]], axis=1)
    # one number a step, as the task's kind says: a lane's tightened half-width, a goal's largest inflation
    tightened = kind_class_for(task).per_step(task, result.tightened)
    # rollouts are for the viewer: 1 mm is plenty, and short numbers make the bulk of the message (3/4 of its
    # bytes at full precision) cheaper to encode, send, record and decode
    samples = np.round(np.asarray(result.sample_states, dtype=np.float64)[:n_samples], 3)
    command = Command(v_ref=float(result.control[0]), omega_ref=float(result.control[1]))
    command.header.stamp_ns = stamp_ns
    # built without validation: the publisher validates what it sends (finite numbers, shapes) exactly once
    plan = Plan.model_construct(
        command=command,
        controls=np.asarray(result.controls, dtype=np.float64).tolist(),
        states=np.asarray(result.states, dtype=np.float64).tolist(),
        cov_xy=cov_xy.tolist(),
        tightened=tightened.reshape(-1).tolist(),
        samples=samples.tolist(),
        sample_costs=np.asarray(result.sample_costs, dtype=np.float64)[:n_samples].tolist(),
        terrain_weights=np.asarray(result.weights, dtype=np.float64).tolist(),
        weights_stale=weights_stale,
        timings_ms={k: float(v) for k, v in {**result.timings_ms, **(extra_timings_ms or {})}.items()},
        critic_costs={k: float(v) for k, v in result.critic_costs.items()},
        effective_samples=float(result.effective_samples),
    )
    plan.header.stamp_ns = stamp_ns
    return plan


class Outputs:
    """The planner's publishers: each plan's command (stamped with its state's stamp) and Plan, and the task."""

    def __init__(self, node: Node, settings: PlanOutputSettings, dt: float, startup: dict[str, float]) -> None:
        self.node, self.s, self.startup = node, settings, startup
        self.cmd = node.publisher("cmd")
        self.plan = node.publisher("plan")
        self.task = node.publisher("task")
        self.costmap = node.publisher("costmap")
        self._grid: tuple[object, OccupancyGrid] | None = None  # the last grid published and its message
        self.ros_plan = Ros2PlanPublisher(node, settings.ros2_plan, dt) if settings.ros2_plan.enabled else None
        self.published = 0
        self.model_version = 0  # the `ModelUpdate.version` planned with, on each Plan
        self.started = time.monotonic()  # when the loop started, for the time to the first command [monotonic s]

    def grid_message(self, task: Task, latest: State | None) -> OccupancyGrid | None:
        """The message of the grid the goal task plans among (recorded and drawn with the task), encoded once per
        grid; None without one, or before the first state (whose frame it is in)."""
        grid = getattr(task, "costmap", None)
        if grid is None or latest is None:
            return None
        if self._grid is None or self._grid[0] is not grid:
            self._grid = (grid, costmap_to_message(grid, latest.header.frame_id))
        msg = self._grid[1]
        msg.header.stamp_ns = time.time_ns()
        return msg

    def publish(self, out: Planned, task: Task, frame_id: str) -> None:
        result = out.result
        cmd = Command(v_ref=float(result.control[0]), omega_ref=float(result.control[1]))
        cmd.header.stamp_ns = out.stamp_ns
        cmd.header.frame_id = "base_link"
        cmd.source = self.node.zid
        self.cmd.put(cmd)
        # the control latency as this process sees it: the state's stamp to the command handed to Zenoh
        state_to_cmd_ms = (time.time_ns() - out.stamp_ns) / 1e6
        if self.published == 0:
            self.startup["to_first_command_s"] = time.monotonic() - self.started
            self.startup["process_age_s"] = process_age_s()
            fields = {k: None if v is None else round(v, 3) for k, v in self.startup.items()}
            self.node.log.info("first command", extra={"fields": fields})
        if self.published % self.s.plan_every == 0:
            try:
                plan = plan_message(result, out.stamp_ns, task, self.s.plan_samples,
                                    {"state_to_cmd": state_to_cmd_ms}, out.weights_stale)
                plan.model_version = self.model_version
                self.plan.put(plan)
            except DecodeError as exc:  # e.g. non-finite sample costs: the command went out, the plan cannot
                self.node.counters.count("plan_invalid")
                self.node.error(f"plan not published: {exc}")
            if self.ros_plan is not None:
                self.ros_plan.put(out, frame_id)
        self.published += 1


class Ros2PlanPublisher:
    """Each plan's nominal trajectory as nav_msgs/Path CDR: in the state's frame, pose k stamped when the plan
    reaches it (the state's stamp + the delay it planned ahead + k dt); on the rmw_zenoh key with its attachment,
    or the bridge key."""

    def __init__(self, node: Node, settings: Ros2PlanOutput, dt: float) -> None:
        import zenoh

        from services.codec import ros2

        assert node.session is not None
        self.ros2, self.settings, self.dt, self.node = ros2, settings, dt, node
        key = settings.key_expr("nav_msgs/msg/Path")
        self.publisher = node.session.declare_publisher(key, encoding=zenoh.Encoding("application/cdr"))
        self.gid = ros2.new_gid(settings.gid_seed)
        self.sequence = 1  # ROS 2 publishers count from 1
        node.log.info("ROS 2 plan (nav_msgs/msg/Path) on %s", key)

    def put(self, out: Planned, frame_id: str) -> None:
        states = np.asarray(out.result.states, dtype=np.float64)
        steps = np.arange(states.shape[0], dtype=np.float64)
        stamps = out.stamp_ns + np.round((out.delay_s + steps * self.dt) * 1e9).astype(np.int64)
        payload = self.ros2.path_cdr(states[:, :3], stamps, frame_id, int(stamps[0]), self.settings.distro)
        attachment = None
        if self.settings.key_style == "rmw_zenoh":
            attachment = self.ros2.Attachment(self.sequence, time.time_ns(), self.gid).to_bytes()
        self.publisher.put(payload, attachment=attachment)
        self.sequence += 1
        with self.node.counters.lock:
            self.node.counters.published += 1

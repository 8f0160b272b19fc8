"""The PushT robot as the planning core sees it, built from the task's facts in `sim_bridge`.

The one bridge from the simulator's constants to the ROS-free core: the evaluation and the
nodes pass `PUSHT_ROBOT` (or a robot model of their own) to the planners.
"""

from __future__ import annotations

from constrained_diffusion_ros.planning.robot import RobotModel
from sim_bridge.scene import (
    AGENT_RADIUS,
    CONTROL_HZ,
    K_P,
    K_V,
    PUSHER_IN_OBSERVATION,
    SIM_HZ,
    WORKSPACE_SIZE,
)

PUSHT_ROBOT = RobotModel(
    pusher_radius=AGENT_RADIUS,
    workspace=(0.0, 0.0, WORKSPACE_SIZE, WORKSPACE_SIZE),
    kp=K_P,
    kv=K_V,
    control_hz=CONTROL_HZ,
    physics_hz=SIM_HZ,
    pusher_in_observation=PUSHER_IN_OBSERVATION,
)

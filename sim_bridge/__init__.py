"""ROS-free PushT simulator: physics, scoring, keypoints and off-screen rendering."""

from sim_bridge.pusht import (
    AGENT_RADIUS,
    CONTROL_HZ,
    COORD_LIMITS,
    GOAL_POSE,
    KEYPOINTS_LOCAL,
    SIM_HZ,
    SUBSTEPS,
    SUCCESS_THRESHOLD,
    WORKSPACE_SIZE,
    PushTBatch,
    PushTSim,
    block_keypoints,
    coverage,
    pusher_transition,
    score_from_coverage,
    seeded_state,
    tee_polygons,
)
from sim_bridge.render import render_scene

__all__ = [
    "AGENT_RADIUS",
    "CONTROL_HZ",
    "COORD_LIMITS",
    "GOAL_POSE",
    "KEYPOINTS_LOCAL",
    "SIM_HZ",
    "SUBSTEPS",
    "SUCCESS_THRESHOLD",
    "WORKSPACE_SIZE",
    "PushTBatch",
    "PushTSim",
    "block_keypoints",
    "coverage",
    "pusher_transition",
    "render_scene",
    "score_from_coverage",
    "seeded_state",
    "tee_polygons",
]

"""The PushT task: scene facts (`scene`), pymunk physics (`physics`), off-screen rendering
(`render`) and the rclpy simulator node (`sim_node`, imported only by ROS users)."""

from sim_bridge.physics import PushTBatch, PushTSim
from sim_bridge.render import render_scene
from sim_bridge.scene import (
    AGENT_RADIUS,
    CONTROL_HZ,
    COORD_LIMITS,
    GOAL_POSE,
    K_P,
    K_V,
    KEYPOINTS_LOCAL,
    SIM_HZ,
    SUBSTEPS,
    SUCCESS_THRESHOLD,
    WORKSPACE_SIZE,
    block_keypoints,
    coverage,
    score_from_coverage,
    seeded_state,
    tee_polygons,
)

__all__ = [
    "AGENT_RADIUS",
    "CONTROL_HZ",
    "COORD_LIMITS",
    "GOAL_POSE",
    "KEYPOINTS_LOCAL",
    "K_P",
    "K_V",
    "SIM_HZ",
    "SUBSTEPS",
    "SUCCESS_THRESHOLD",
    "WORKSPACE_SIZE",
    "PushTBatch",
    "PushTSim",
    "block_keypoints",
    "coverage",
    "render_scene",
    "score_from_coverage",
    "seeded_state",
    "tee_polygons",
]

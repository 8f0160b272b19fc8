"""What turns observations and zones into setpoints, shared by the policy node and the
evaluation: constraint configurations (`config`), the robot model (`robot`), planners
(`planners`), the shield (`shield`) and the chunk executor (`executor`)."""

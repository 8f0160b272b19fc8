"""What turns observations and zones into setpoints, shared by the policy node and the
evaluation: constraint configurations (`config`), the robot model (`robot`), planners
(`planners`), the shield (`shield`) and the lockstep loop (`lockstep`), which executes chunks
from an action queue (`action_queue`).

The real-time mode adds a controller (`realtime`) fed by a control clock (`clock`), whose plans
are made in the background by a worker: the jobs, results and messages they exchange and the
interface both workers implement (`plan_jobs`), a thread (`thread_worker`) or a supervised child
process (`planning_process`). What asks the operating system for priorities and reads /proc is in
`os_scheduling`."""

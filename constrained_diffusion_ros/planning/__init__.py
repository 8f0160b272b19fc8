"""What turns observations and zones into setpoints, shared by the policy node and the
evaluation: constraint configurations (`config`), the robot model (`robot`), planners
(`planners`), the shield (`shield`), and the one chunk loop (`chunk_loop`) that executes chunks
from an action queue (`action_queue`) in the evaluation, the delay study, lockstep mode and live.

The loop asks a planning worker for chunks: the jobs, results and messages they exchange and the
interface every worker implements are in `plan_jobs`; a simulated worker plans in the caller's
thread with a chosen delay (`simulated_worker`), a thread (`thread_worker`) or a supervised child
process (`planning_process`) plans in the background. Live, a control clock (`clock`) sends the
setpoints, which `sound_setpoints` has the last word on; what asks the operating system for
priorities and reads /proc is in `os_scheduling`."""

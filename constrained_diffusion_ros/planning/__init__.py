"""What turns observations and zones into setpoints, shared by the policy node and the
evaluation: constraint configurations (`config`), the robot model (`robot`), planners
(`planners`), the shield (`shield`), and the one chunk loop (`chunk_loop`) that executes chunks
from an action queue (`action_queue`) in the evaluation, the delay study, lockstep mode and live.

The loop asks a planning worker for chunks: the jobs, results and messages they exchange and the
interface every worker implements are in `plan_jobs`; a simulated worker plans in the caller's
thread with a chosen delay (`simulated_worker`). The workers that plan in the background, the
control clock and the operating system's part are the live runtime's (`runtime`)."""

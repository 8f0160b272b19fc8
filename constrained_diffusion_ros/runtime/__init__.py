"""What makes the chunk loop live, apart from the method it runs (`planning`): the loop on the
wall clock (`live_loop`), the workers that plan in the background, a supervised child process
(`planning_process`) or a thread (`thread_worker`), the control clock that sends setpoints at
the control rate (`clock`), and the one module that asks the operating system for priorities
and reads /proc (`os_scheduling`)."""

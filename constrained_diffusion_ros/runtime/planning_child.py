"""The planning child's side, and the messages both sides speak: the node (`PlanningProcess`)
starts a plain interpreter on `child_command` (`spawn`), which runs `serve`; they talk over a
socket pair in the messages of plan_jobs.py (`Request`, `Reply`), each a kind and a pickled
payload.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import pickle
import socket
import struct
import subprocess
import sys
import termios
import time
from dataclasses import replace
from multiprocessing.connection import Connection
from pathlib import Path

import torch

from constrained_diffusion_ros.planning.plan_jobs import Reply, Request, plan_chunk
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.runtime.os_scheduling import lower_own_priority, scheduling
from constrained_diffusion_ros.sampling.sampler import Interrupted


def encode(kind: Request | Reply, payload: object) -> bytes:
    """(kind, pickled payload): the kind always reads back, even where the payload cannot (a
    class the other side cannot import), so every job gets its reply. The kind goes as a plain
    string."""
    data = pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)
    return pickle.dumps((str(kind), data), protocol=pickle.HIGHEST_PROTOCOL)


def send(connection: Connection, kind: Request | Reply, payload: object) -> None:
    connection.send_bytes(encode(kind, payload))


def serve(descriptor: int, threads: int, niceness: int, idle: bool = False) -> None:
    """The child: plan each job with the planner and generator it was last given, until told
    to stop or the node's end of the socket closes (the node died, even by SIGKILL: then a
    plan in flight stops, its answer cannot be sent, and the child exits without a word)."""
    connection = Connection(descriptor)
    with contextlib.suppress(OSError, EOFError):  # the node is gone: nobody to answer
        _serve(connection, threads, niceness, idle)


def _serve(connection: Connection, threads: int, niceness: int, idle: bool) -> None:
    """`serve`'s loop; returns when told to stop, raises OSError or EOFError when the node's
    end of the socket is closed."""
    lower_own_priority(niceness, idle)  # before torch starts threads: they inherit it
    send(connection, Reply.SCHEDULING, (scheduling(), 0.0))  # what it got, not what was asked
    torch.set_num_threads(threads)
    policy, planner, zones = None, None, None
    generator = torch.Generator()
    while True:
        kind, data = pickle.loads(connection.recv_bytes())
        if kind == Request.STOP:
            return
        began = time.perf_counter()
        try:  # a fault is reported to the node; the child keeps serving
            payload = pickle.loads(data)
            if kind == Request.POLICY:
                policy = payload
            elif kind == Request.PLANNER:
                planner = ConstrainedPlanner(policy, *payload)
                planner.prepare_sampling()  # before the first job, not in it
            elif kind == Request.SEED:
                generator.manual_seed(payload)
            elif kind == Request.JOB:
                job, same_zones = payload
                job = replace(job, zones=zones) if same_zones else job
                zones = job.zones
                # Any message while it plans makes the plan worthless (the node sends a job
                # only to an idle child): a cancel, a new seed or planner, a stop.
                chunk = plan_chunk(planner, job, generator, connection.poll)
            # Request.CANCEL: the plan it stopped is answered already
        except Interrupted:
            send(connection, Reply.CANCELLED, (None, time.perf_counter() - began))
            continue
        except Exception as error:
            # Only a job's reply ends it.
            reply = Reply.JOB_ERROR if kind == Request.JOB else Reply.ERROR
            send(connection, reply, (f"{type(error).__name__}: {error}",
                                      time.perf_counter() - began))
            continue
        if kind == Request.JOB:  # outside the try: a send that fails is the node gone
            send(connection, Reply.CHUNK, (chunk, time.perf_counter() - began))


def unread(connection: Connection) -> int:
    """Bytes sent on a socket that its peer has not read yet (0 where that cannot be told)."""
    try:
        queued = fcntl.ioctl(connection.fileno(), termios.TIOCOUTQ, bytes(4))
    except OSError:
        return 0
    return struct.unpack("i", queued)[0]


def child_command(descriptor: int, threads: int, niceness: int, idle: bool) -> list[str]:
    """The planning child's command line: a plain interpreter that runs `serve`."""
    # SIGINT ignored: Ctrl-C in a terminal reaches the whole process group, and the child ends
    # with its node (told to stop, or finding the socket closed), not with a traceback.
    code = (f"import signal; signal.signal(signal.SIGINT, signal.SIG_IGN); "
            f"from {__name__} import serve; serve({descriptor}, {threads}, {niceness}, {idle})")
    return [sys.executable, "-c", code]


def spawn(threads: int, niceness: int, idle: bool) -> tuple[subprocess.Popen, Connection]:
    """A new child on a socket pair: a plain interpreter, not multiprocessing's spawn (that one
    would run the caller's main script again in the child); fork is unsafe beside DDS threads.
    It runs `threads` torch threads (OMP_NUM_THREADS set on purpose) and imports this package
    from where the node does."""
    package_root = str(Path(__file__).resolve().parents[2])
    environment = {**os.environ, "OMP_NUM_THREADS": str(threads),
                   "PYTHONPATH": os.pathsep.join(
                       filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
    ours, theirs = socket.socketpair()
    try:
        process = subprocess.Popen(child_command(theirs.fileno(), threads, niceness, idle),
                                   env=environment, pass_fds=[theirs.fileno()],
                                   stdin=subprocess.DEVNULL)
    except BaseException:
        ours.close()
        raise
    finally:
        theirs.close()
    return process, Connection(ours.detach())


def reap(process: subprocess.Popen, timeout: float = 5.0) -> int:
    """A child's exit code once its socket has closed; one that still lives `timeout` s later
    is not to be trusted, and is killed."""
    try:
        return process.wait(timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.wait()

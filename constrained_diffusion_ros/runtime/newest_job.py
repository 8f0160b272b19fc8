"""The hand-off of a helper that owns a worker thread and serves only the newest job: a job not
started yet is replaced by the next, and `shutdown` stops and joins the thread, as tf2_ros's
listener owns its thread. Its users are the keep-out mask builder (runtime/mask_builder.py)
and the planning thread (runtime/thread_worker.py)."""

from __future__ import annotations

import threading
from collections.abc import Callable


class NewestJobThread:
    """Base of such helpers: `_job` (None: none waiting) and `_stopping` are guarded by `_wake`;
    the thread runs `target`, which waits with `_wait_for_job` under `_wake`."""

    def __init__(self, target: Callable[[], None], name: str) -> None:
        self._wake = threading.Condition()
        self._job = None
        self._stopping = False
        self._thread = threading.Thread(target=target, name=name, daemon=True)

    def _wait_for_job(self) -> bool:
        """Under `_wake`: until a job waits (True) or the helper stops (False)."""
        while self._job is None and not self._stopping:
            self._wake.wait()
        return not self._stopping

    def shutdown(self, timeout: float = 5.0) -> None:
        with self._wake:
            self._stopping = True
            self._wake.notify()
        self._thread.join(timeout)

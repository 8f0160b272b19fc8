"""Keep-out masks built off the thread that answers zones: the node's helper that owns a
builder thread (`MaskBuilder`); what building a mask is stays with the zones
(`zones.grid.build_mask`)."""

from __future__ import annotations

from collections.abc import Callable

from constrained_diffusion_ros.runtime.newest_job import NewestJobThread
from constrained_diffusion_ros.zones.area import Bounds
from constrained_diffusion_ros.zones.grid import BuiltMask, MaskCaps, build_mask

DEFAULT_CAPS = MaskCaps()


class MaskBuilder(NewestJobThread):
    """Builds keep-out masks on a thread of its own, so that the thread which answers zones and
    observations never waits for one: a fine mask costs a scan and a union that a zone dropped
    meanwhile must not queue behind.

    Only the newest mask matters (a mask replaces the previous one): `submit` replaces one not
    started yet, and a result whose mask was superseded while it was built is not handed over.
    `on_built` is called on the builder's thread with each `BuiltMask`; the owner applies it on
    its own thread. Like tf2's listener, the helper owns its thread; `shutdown` ends it.
    """

    def __init__(self, on_built: Callable[[BuiltMask], None], caps: MaskCaps = DEFAULT_CAPS,
                 workspace: Bounds | None = None) -> None:
        super().__init__(self._run, "mask_builder")
        self._on_built, self.caps, self.workspace = on_built, caps, workspace
        self._job: tuple[int, dict, float | None] | None = None
        self._sequence = 0
        self._thread.start()

    def submit(self, stamp: float | None = None, **grid: object) -> int:
        """Build `grid_polygons(**grid)` under the caps; returns the mask's sequence number."""
        with self._wake:
            self._sequence += 1
            self._job = (self._sequence, grid, stamp)
            self._wake.notify()
            return self._sequence

    @property
    def latest(self) -> int:
        """The sequence number of the newest mask submitted."""
        return self._sequence

    def _run(self) -> None:
        while True:
            with self._wake:
                if not self._wait_for_job():
                    return
                (sequence, grid, stamp), self._job = self._job, None
            built = build_mask(grid, self.caps, self.workspace, sequence, stamp)
            if sequence == self._sequence:  # not superseded while it was built
                self._on_built(built)

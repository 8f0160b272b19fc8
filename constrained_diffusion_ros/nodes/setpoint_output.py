"""Setpoints out to ROS for the policy node: one path for every setpoint it sends.

`SetpointOutput` owns the setpoint publisher and the message in force: each setpoint is made
sound (`SoundSetpoints`), stamped with its observation's stamp, kept as the one in force and
published now or by the control clock's next tick; a setpoint replaced is never sent after it.
It counts setpoints that went out inside a zone (`violations`).

It fails safe by going quiet, as a robot driver's command timeout expects (the robot holds its
last target, then stops on its own watchdog): `halt()` ends publishing for good (the node's zone
handling died), and with a `watchdog_s` the clock's repeats are withheld while the executor that
answers zones has not `beat()` for that long (a stalled executor cannot answer a new zone, so
the setpoint in force is no longer known to respect the zones in force). Going quiet, rather
than repeating the last setpoint, leaves no doubt on the robot's side that the node is not
answering.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy._rclpy_pybind11 import RCLError
from rclpy.node import Node

from constrained_diffusion_ros.planning.sound_setpoints import SoundSetpoints
from msg_schemas import TOPICS, qos_profile
from msg_schemas.conversions import point_message


class SetpointOutput:
    def __init__(self, node: Node, sound: SoundSetpoints, watchdog_s: float = 0.0) -> None:
        self.node, self.sound = node, sound
        self.publisher = node.create_publisher(PointStamped, TOPICS["setpoint"].name,
                                               qos_profile(TOPICS["setpoint"], "publisher"))
        self.in_force: PointStamped | None = None
        self.violations = 0
        self.watchdog_s, self.alive_at = watchdog_s, time.monotonic()
        self.withheld = 0  # clock ticks not sent: the executor had stalled
        self.halted = False
        self.paused = False  # inactive (a lifecycle node deactivated): nothing is published
        self._lock = threading.Lock()

    def beat(self) -> None:
        """The executor is alive (called from one of its timers)."""
        self.alive_at = time.monotonic()

    def halt(self) -> None:
        """No setpoint goes out after this returns, from any thread."""
        with self._lock:
            self.halted = True

    def pause(self, paused: bool = True) -> None:
        """Nothing published while paused (the setpoint in force is kept, and sent again once
        it resumes); from any thread, as `halt`."""
        with self._lock:
            self.paused = paused

    def send(self, setpoint: np.ndarray | None, stamp, pusher: np.ndarray | None,
             publish: bool = True) -> float | None:
        """`setpoint` (2,) made sound (`pusher`: the last plausible position, for a stand-in),
        stamped `stamp`, in force from now and published now if `publish`. Returns when it was
        published (time.monotonic()), or None."""
        if setpoint is None or stamp is None:
            return None
        unsound = self.sound.unsound
        setpoint = self.sound(setpoint, pusher)
        if self.sound.unsound != unsound:
            self.node.get_logger().error("no sound setpoint (zones leave no free space, or a "
                                         "non-finite action): holding the pusher",
                                         throttle_duration_sec=1.0)
        message = point_message(setpoint, stamp)
        sent = None
        with self._lock:  # a setpoint replaced is never sent after it
            self.in_force = message
            if publish and not (self.halted or self.paused):
                self.publisher.publish(message)
                sent = time.monotonic()
        self.violations += self.sound.inside_zone(setpoint)
        return sent

    def withdraw(self) -> None:
        """No setpoint in force until the next `send`: the run it was for has ended (a reset);
        no tick sends it after this returns."""
        with self._lock:
            self.in_force = None

    def status(self) -> dict[str, object]:
        return {"violations": self.violations, "unsound_setpoints": self.sound.unsound,
                "no_free_space": self.sound.no_free_space, "ticks_withheld": self.withheld}

    def repeat(self) -> None:
        """The setpoint in force again (the clock's tick; a lockstep answer that was lost),
        if there is one; nothing to wait on but the short lock around sending."""
        with self._lock:
            if self.in_force is None or self.halted or self.paused:
                return
            if self.watchdog_s and time.monotonic() - self.alive_at > self.watchdog_s:
                self.withheld += 1
                return
            try:
                self.publisher.publish(self.in_force)
            except RCLError:  # shutting down: the context went away under the clock
                if self.node.context.ok():
                    raise

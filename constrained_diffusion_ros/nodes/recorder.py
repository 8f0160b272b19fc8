"""recorder: writes every topic of the contract into a rosbag2 directory (MCAP storage).

No rosbag2 wheels exist for a PyPI ROS install, so the bag is written with the `rosbags` library.
Subscriptions are raw: messages arrive CDR-serialized and are stored as they came, with the
contract's QoS as the offered profile and the message definitions of the ROS 2 Jazzy typestore,
so `ros2 bag`, MCAP viewers and `rosbags.rosbag2.Reader` all read the bag.

Metadata: metadata.yaml's `custom_data` (also in the MCAP file's `rosbag2` metadata record) gets
  `message_counts`: JSON object, contract topic -> messages recorded;
  `trial_metadata`: the JSON content of the `metadata_file` parameter, read at start and again at
  close, so a trial can write its results there before it stops the recorder.
Both values are JSON strings, as custom_data holds strings only.

SIGINT or SIGTERM closes the bag with every message received so far; a bag directory that already
exists is refused (rosbag2 bags are never appended to). metadata.yaml is written when the bag opens
and what was received is handed to the operating system twice a second: if the recorder is killed
(SIGKILL, a crash), `recover_bag DIR` indexes everything written up to then.

Run: `recorder --ros-args -p output:=trials/run1 -p metadata_file:=trials/run1.json`.
"""

from __future__ import annotations

import sys

from node_support.parameters import Param, answered_help

PARAMETERS = (
    Param("output", "trials/bag", "rosbag2 directory (MCAP) to write; must not exist yet",
          read_only=True),
    Param("metadata_file", "", "JSON file stored in the bag's metadata (read at start and at "
          "close); empty: none", read_only=True),
)


def main(args: list[str] | None = None) -> int:
    if answered_help(args, "recorder", __doc__, PARAMETERS):
        return 0  # before rclpy and rosbags are imported: --help at once
    from constrained_diffusion_ros.nodes.recorder_impl import record

    return record(args, PARAMETERS)


if __name__ == "__main__":
    sys.exit(main())

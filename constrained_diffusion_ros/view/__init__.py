"""The live view: the PushT scene top down for the Foxglove app (`scene`), and the zones an
operator draws there (`zone_requests`). ROS-free; `nodes/view_node.py` feeds it and serves it."""

"""The live view: the PushT scene top down for the Foxglove app (`scene`), and the zones an
operator draws there (`zone_requests`). ROS-free; the view node (`nodes/view_node_impl.py`)
feeds it and serves it."""

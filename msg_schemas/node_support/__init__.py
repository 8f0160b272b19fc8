"""What every node of the package shares besides the interface itself: declared parameters with
descriptors and `--help` (`parameters`), and spinning, start-up and log plumbing (`spin`). Kept
under `msg_schemas`, apart from the contract and the conversions, because it is the one package
that both the simulator's node (`sim_bridge`) and the policy's nodes may import (imports run
one way: msg_schemas <- sim_bridge <- constrained_diffusion_ros)."""

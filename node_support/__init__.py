"""What every node of the package shares besides the interface itself: declared parameters with
descriptors and `--help` (`parameters`), and spinning, start-up and log plumbing (`spin`). A
package of its own below the simulator, so that both the simulator's node (`sim_bridge`) and
the policy's nodes may import it (imports run one way: msg_schemas <- node_support <-
sim_bridge <- constrained_diffusion_ros); `msg_schemas` keeps the contract and conversions."""

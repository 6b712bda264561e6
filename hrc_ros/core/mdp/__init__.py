"""The paper's MDP over the full state (MODEL.md 5): the factored Bellman operator and value /
policy iteration (`solver`, fused sweep kernels in `_kernels`), and the policy files it writes
(`policy`)."""

"""mmpc.rl: the batch optimizer as a safe action layer for reinforcement learning (planned)."""

"""Reinforcement learning: environments, PPO, networks, policy checkpoints, training results."""

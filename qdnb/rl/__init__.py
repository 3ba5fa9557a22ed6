"""Reinforcement learning: TD3 (its twin critic and policy-gradient steps), the replay
buffer, and the RL agents that serve as baselines (``agents``)."""

"""Networks and reinforcement learning pieces."""

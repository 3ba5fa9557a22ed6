"""Reinforcement learning: TD3 (its twin critic and policy-gradient steps), the replay
buffer, the TD3 agent (``agents``) and Chapter 3's other policy-gradient baselines,
one file each: ``sac``, ``rnd``, ``cemrl``, ``p3s``, ``agac``, ``diayn``."""

"""The Quality-Diversity Transformer (Chapter 4, Sections 4.4.3-4.5.5):
``data`` builds datasets of trajectories from QD repertoires, ``model`` is the
behaviour-conditioned causal transformer of Algorithm 8, ``train`` fits it by
supervised learning and ``evaluate`` plays it in the environment."""

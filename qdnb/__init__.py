"""qdnb: the helper package behind the reproducible book of the thesis
"Diversity based exploration for deep reinforcement learning".

The sub-packages mirror the book: ``envs`` (tasks), ``qd`` (quality-diversity
algorithms), ``rl`` (networks and reinforcement learning), plus the plumbing that
runs notebooks and builds the book (``scale``, ``paths``, ``provenance``,
``runner``, ``thesis``, ``plotting``).  Importing ``qdnb`` itself is cheap: JAX is
only imported by the modules that need it.
"""

__version__ = "0.1.0"

"""qdnb: the helper package behind the reproducible book of the thesis
"Diversity based exploration for deep reinforcement learning".

Layers, each importing only from itself and those below it (``tests/test_layers.py``):
``core`` (paths, configs, files, loops, the ``Evaluation``/``Algorithm`` protocol) →
``envs`` and ``nets`` → ``rl`` → ``qd`` → ``models`` (the QDT, Flow Lenia and the FLT) →
``chapters`` (one module per chapter: its configs, methods and experiment) →
``plotting`` → ``book`` (the chapter registry, the runner, run manifests).  Importing
``qdnb`` itself is cheap: JAX is only imported by the modules that need it.
"""

__version__ = "0.1.0"

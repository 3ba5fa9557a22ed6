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

# One XLA host device per core on CPU, asked for before JAX starts its backends
# (``qdnb.core.sharding.configure_host_devices``; ``QDNB_DEVICES=1`` turns it off).
from qdnb.core.sharding import configure_host_devices as _configure_host_devices  # noqa: E402

_configure_host_devices()

# MuJoCo picks its off-screen OpenGL when it is first imported (brax imports it): EGL, which
# Mesa provides without a display or a GPU, for the book's robot videos
# (``qdnb.envs.render``); a MUJOCO_GL set by the user wins.
import os as _os  # noqa: E402

_os.environ.setdefault("MUJOCO_GL", "egl")

"""The top layer: the chapter registry, the notebook runner and the book build,
run manifests (``summary.json``) and the thesis's transcribed tables.  Importing it
loads no JAX (``python -m qdnb list`` stays instant)."""

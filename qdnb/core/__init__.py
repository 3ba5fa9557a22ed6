"""The bottom layer, imported by every other: paths, scales and config hashes,
atomic files, pytree helpers, the jitted chunked loop, and the ``Evaluation`` /
``Algorithm`` protocol every search shares.  Importing the package loads no JAX."""

import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.loops import scan_in_chunks


def test_chunked_scan_equals_one_scan():
    step = lambda c: (c * 1.5 + 1.0, c)
    carry, outs = scan_in_chunks(step, jnp.float32(0.0), 7, 3, progress=False)
    expected, c = [], 0.0
    for _ in range(7):
        expected.append(c)
        c = c * 1.5 + 1.0
    np.testing.assert_allclose(outs, expected, rtol=1e-6)
    np.testing.assert_allclose(carry, c, rtol=1e-6)
    seconds = []
    scan_in_chunks(step, jnp.float32(0.0), 7, 3, progress=False, chunk_seconds=seconds)
    assert len(seconds) == 3 and all(s > 0 for s in seconds)  # chunks of 3, 3 and 1 steps


def test_bad_lengths_are_errors():
    with pytest.raises(ValueError, match="positive"):
        scan_in_chunks(lambda c: (c, c), 0.0, 0, 3)

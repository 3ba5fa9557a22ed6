"""A chapter's claims as ``summary.json`` records them, for the book's scorecard.

Each claim is one record: a stable ``id`` (the same claim at every scale), the
``claim`` in the thesis's words and names, its ``status`` (``holds``, ``fails`` or
``cannot show``: the run could not test it, e.g. a method never reached the goal
the claim measures) and the ``numbers`` behind the verdict.
"""

from __future__ import annotations

import numpy as np

HOLDS, FAILS, CANNOT_SHOW = "holds", "fails", "cannot show"
STATUSES = (HOLDS, FAILS, CANNOT_SHOW)


def record(claim_id: str, claim: str, status: str | bool, numbers: str) -> dict[str, str]:
    """One claim's record; ``status`` may be a bool (``True``: holds, ``False``: fails)."""
    if isinstance(status, bool):
        status = HOLDS if status else FAILS
    if status not in STATUSES:
        raise ValueError(f"a claim's status is one of {', '.join(STATUSES)}, got {status!r}")
    if not claim_id or not claim:
        raise ValueError("a claim needs an id and a text")
    return {"id": claim_id, "claim": claim, "status": status, "numbers": numbers}


def finite_mean(values) -> float:
    """The mean over the seeds whose value is finite (a diverged seed, or one that could
    not measure it, is NaN); NaN, without a warning, if none is."""
    values = np.asarray(values, float)
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else float("nan")


def held(claims: list[dict[str, str]]) -> int:
    """How many of ``claims`` hold."""
    return sum(c["status"] == HOLDS for c in claims)

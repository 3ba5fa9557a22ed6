"""Chapter 4's reproducibility experiment (Sections 4.3-4.5.4), one environment
at a time: run ME, ME-LS, PGA-ME, PGA-ME-LS and ME-Sampling on the same budget
of environment steps, then put every final repertoire through the same tests:

- the accuracy experiment (Section 4.5.2): for each goal descriptor (the centroids
  of a CVT of the descriptor space), play the stored policy whose descriptor is
  nearest to the goal over fresh episodes; average distance to the goal and spread;
- the reassessment (Table 4.5): play every stored policy again and insert it into
  an empty repertoire;
- three representative policies (Figures 4.3-4.5), chosen by a fixed rule and
  played over many episodes.

``run_environment`` does all of it and returns plain numpy arrays; the
environments are independent, so ``run_environments`` runs them in concurrent
threads (JAX releases the interpreter while it computes: on a 2-core CPU the
two simulations then share the cores, about 1.5x faster than one after the other).

The page's files: ``settings`` (the config, the boxes, the scales), ``experiment``
(``run_environment`` and the saved repertoires) and ``claims`` (the claims and
``summary_results``).  Their names are gathered here.
"""

from qdnb.chapters.ch4_reproducibility.claims import (
    CLAIM_METRICS,
    CLAIM_PAIRS,
    CLAIM_STATEMENTS,
    claim_checks,
    comparisons,
    summary_results,
)
from qdnb.chapters.ch4_reproducibility.experiment import (
    METHODS,
    ONE_EPISODE,
    EnvironmentResult,
    MethodResult,
    build_algorithms,
    load_repertoires,
    representative_cells,
    run_environment,
    run_environments,
    save_repertoires,
    seed_scores,
)
from qdnb.chapters.ch4_reproducibility.settings import (
    COVERAGE_TARGET,
    LOW_SPREAD,
    REACH_QUANTILE,
    REACH_STEP,
    REPRESENTATIVE_QUANTILES,
    SCALES,
    THESIS_ANT_OMNI_BOX,
    Config,
    ReproducibilityConfig,
    cells_for_coverage,
    fitness_offset,
    reach_bound,
)

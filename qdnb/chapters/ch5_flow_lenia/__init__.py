"""Chapter 5's experiments: the system the FLT learns, its evaluation against two
baselines, and the surprise search of Section 5.3.2.

- ``pick_system``: the thesis trains on one Flow Lenia system, varying only the
  initial matter and parameter map (Section 5.3.1, footnote 2), and does not say
  which.  Systems are drawn from Table 5.1 in order and the first worth
  predicting is kept (``SystemCriteria``: its matter stays localised, its ending
  depends on the initial state, its pattern settles).  The rule looks at the
  simulations only, never at a predictor's error.
- ``evaluate``: held-out episodes from fresh initial states, the FLT unrolled
  from ``x_0`` alone, and the persistence (every frame is ``x_0``) and mean-frame
  (each frame is the training episodes' mean frame at that timestep) predictors
  on the same episodes.
- ``surprise_search``: MAP-Elites over initial states (matter and parameter
  patches), with the FLT's final-frame error on ``A`` as fitness ("surprise") and
  two descriptors of the final pattern (``pattern_descriptors``).

``run(cfg, key)`` chains the stages in the notebook's order (``random_gallery``,
``pick_system``, ``compare_p0``, the FLT's training, ``evaluate``, ``diagnose``, the
surprise search) into a frozen ``Result``; ``summary_results`` writes its summary.

The chapter's files: ``settings`` (the world, the config, its scales), ``system``
(``pick_system``, the gallery, the P0 comparison), ``evaluation`` (``evaluate`` and
``diagnose``), ``search`` (the surprise search), ``experiment`` (``run``) and ``claims``
(the claims and ``summary_results``).  Their names are gathered here.
"""

from qdnb.chapters.ch5_flow_lenia.claims import model_results, summary_results, variant_claims
from qdnb.chapters.ch5_flow_lenia.evaluation import (
    METHODS,
    OUR_FLT,
    THESIS_FLT,
    Diagnosis,
    HeldOut,
    best_model,
    diagnose,
    evaluate,
)
from qdnb.chapters.ch5_flow_lenia.experiment import Result, run, surprise_search, train_variant
from qdnb.chapters.ch5_flow_lenia.search import (
    SearchResult,
    SurpriseSearch,
    centre_of_mass,
    offsets,
    pattern_descriptors,
    signed,
    spearman,
)
from qdnb.chapters.ch5_flow_lenia.settings import (
    PAPER_FLT,
    SCALES,
    SMALL_FLT,
    SMALL_VARIANT,
    TINY_FLT,
    VARIANT_PICK,
    VARIANT_SHARE,
    Config,
    FlowLeniaChapterConfig,
    lenia_world,
)
from qdnb.chapters.ch5_flow_lenia.system import (
    P0_RULES,
    Gallery,
    P0Comparison,
    SystemChoice,
    SystemCriteria,
    compare_p0,
    occupancy,
    pick_system,
    probe_statistics,
    random_gallery,
    world_statistics,
)

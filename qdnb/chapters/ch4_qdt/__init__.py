"""The QDT chapter's experiments on one environment (Sections 4.5.1-4.5.5).

For every full seed (``QDTConfig.full_seeds``): the accuracy experiment of the
four repertoires on the evaluation goals, and of the policies the zone selection
keeps from each (the QDT's demonstrators); the datasets (Section 4.4.4) of ME,
ME-LS, PGA-ME, PGA-ME-LS and Naive; a QDT trained on each (Figure 4.7, Table 4.4,
Figure 4.14); and a QDT trained on each pruned ME-LS dataset (Figures 4.10 and
4.11).  The other seeds do the same for ME and ME-LS only (``CLAIM_SOURCES``, what
the accuracy claim compares).  Everything comes back as frozen results with the
seeds on axis 0 (``EnvironmentResult``: ``Scores`` and ``QDTRun`` per method); the
derived values (``selection_summary``, ``data_floor``, ``nearest_half``), the
claim (``claim_checks``) and ``summary_results`` are in ``claims``; the notebook
draws and tabulates.

The page's files: ``settings`` (Table 4.3's config and the scales), ``repertoires``
(Chapter 4's repertoires, the data), ``results`` (what a run keeps), ``experiment``
(``run_environment``: the datasets, the training, the evaluation), ``episodes`` (the
episodes the page plays) and ``claims`` (the claim and ``summary_results``).  Their
names are gathered here.
"""

from qdnb.chapters.ch4_qdt.claims import (
    QDT_CLAIM_RIVALS,
    claim_checks,
    data_floor,
    nearest_half,
    selection_summary,
    summary_results,
)
from qdnb.chapters.ch4_qdt.episodes import GoalEpisodes, goal_episodes
from qdnb.chapters.ch4_qdt.experiment import (
    DRY_RUN_GOALS,
    Setting,
    demonstrations,
    goals_in_a_dry_run,
    num_seeds_of,
    qdt_model,
    run_environment,
    run_environments,
    setting,
    untrained_run,
)
from qdnb.chapters.ch4_qdt.repertoires import load_or_recompute_repertoires, repertoire_path
from qdnb.chapters.ch4_qdt.results import EnvironmentResult, QDTRun, Scores, by_name
from qdnb.chapters.ch4_qdt.settings import (
    CLAIM_SOURCES,
    DATASETS,
    METHODS,
    SCALES,
    Config,
    QDTConfig,
    QDTTask,
)

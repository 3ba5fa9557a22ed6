"""Chapter 3's experiment: QD-PG, its ablations, TD3 and PGA-ME on one environment.

``run_environment(cfg, env_name, key)`` runs every method of the config on the
same environment-step budget (each method's seeds at once, ``vmap``), and
returns, per method, the history of every iteration (performance, grid
coverage, environment steps, every evaluated policy's descriptor and fitness)
and the final MAP-Elites grids.

Performance follows Table 3.4: the episode return on Point-Maze and Ant-Trap,
the best reward of the episode (minus the closest distance to the goal) on
Ant-Maze.  For the MAP-Elites methods the performance at an iteration is the
best solution of the grid; for TD3 it is the greedy episode of its actor.

The chapter's files: ``settings`` (Table 3.2's tasks, the config, its scales),
``methods`` (the registry of every method Chapter 3's pages run), ``experiment`` (the
loop over an environment's methods and seeds, its results, QD-PG's runs for the other
pages), ``measures`` (the exit zone, reachable cells, steps to the goal), ``claims``
(the page's claims and summary), ``adaptation`` (Section 3.7's fast adaptation and the
hand-made Point-Maze path) and ``readings`` (the A/B of QD-PG's readings at Table 3.2's
budget, as the page's tables).  Their names are gathered here.
"""

from qdnb.chapters.ch3_qdpg.adaptation import (
    FastAdaptation,
    HandPath,
    adaptation_picks,
    fast_adaptation,
    hand_path,
    waypoint_policy,
)
from qdnb.chapters.ch3_qdpg.claims import (
    CLAIM_IDS,
    beats,
    claims,
    method_summaries,
    per_seed,
    summary_results,
)
from qdnb.chapters.ch3_qdpg.experiment import (
    EnvironmentResult,
    MethodResult,
    build_algorithms,
    final_grid,
    load_method_result,
    load_or_recompute_qdpg,
    policy_network,
    qdpg_path,
    run_environment,
    run_method,
    save_method_result,
    save_qdpg_results,
    shown_policy,
    steady_rate,
)
from qdnb.chapters.ch3_qdpg.measures import (
    ANTMAZE_SOLVED,
    goal_hits,
    grid_coverage,
    in_exit_zone,
    reachable_cells,
    reachable_coverage,
    reached_goal,
    steps_to_exit,
    until_goal,
)
from qdnb.chapters.ch3_qdpg.methods import METHODS, QDPG_METHODS
from qdnb.chapters.ch3_qdpg.readings import (
    AB_RESULTS,
    PEER_RESULTS,
    PUBLISHED_POINTMAZE,
    READING_EXITS_SHARE,
    READING_MIN_SEEDS,
    READINGS,
    STATE_PARTS,
    divergence_rows,
    exits_needed,
    published_rows,
    read_json,
    reading_exits,
    reading_needs_more_seeds,
    reading_rows,
)
from qdnb.chapters.ch3_qdpg.settings import (
    ANT_PAPER,
    ANT_SMALL,
    ANT_TINY,
    ENVIRONMENTS,
    POINTMAZE_PAPER,
    SCALES,
    SMALL_POINTMAZE_STEPS,
    Config,
    QDPGConfig,
    QDPGTask,
    fitness_offset,
    make_task_env,
)

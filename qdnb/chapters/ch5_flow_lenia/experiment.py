"""Chapter 5's experiment: the stages in the notebook's order, chained into one frozen
result.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import jax

from qdnb.chapters.ch5_flow_lenia.evaluation import OUR_FLT, best_model, diagnose, evaluate
from qdnb.chapters.ch5_flow_lenia.search import SurpriseSearch
from qdnb.chapters.ch5_flow_lenia.system import (
    SystemCriteria,
    compare_p0,
    pick_system,
    random_gallery,
)
from qdnb.models.lenia import flow_lenia as fl
from qdnb.models.lenia.flt import (
    FLT,
    TrainResult,
    make_model,
    train,
)

if TYPE_CHECKING:
    from qdnb.chapters.ch5_flow_lenia.evaluation import Diagnosis, HeldOut
    from qdnb.chapters.ch5_flow_lenia.search import SearchResult
    from qdnb.chapters.ch5_flow_lenia.settings import FlowLeniaChapterConfig
    from qdnb.chapters.ch5_flow_lenia.system import Gallery, P0Comparison, SystemChoice


@dataclass(frozen=True)
class Result:
    """One run of the chapter (``run``): every stage's result, in the chapter's order."""

    cfg: FlowLeniaChapterConfig
    gallery: Gallery
    choice: SystemChoice
    p0: P0Comparison
    trained: TrainResult
    held_out: HeldOut
    diagnosis: Diagnosis
    search: SearchResult
    variant: TrainResult | None = None  # ours (``cfg.variant``), and its held-out scores
    variant_held_out: HeldOut | None = None

    @property
    def searched(self) -> str:
        """Which model the surprise search ran on: the better predictor of the final
        frame (``best_model``)."""
        return best_model(self.held_out, self.variant_held_out)

    @property
    def mass_drift_max(self) -> float:
        """The largest relative change of mass over every episode simulated."""
        return float(
            max(
                self.gallery.drift,
                self.trained.max_drift,
                self.held_out.drift.max(),
                self.search.history["drift"].max(),
            )
        )


def train_variant(
    cfg: FlowLeniaChapterConfig,
    system: fl.System,
    key: jax.Array,
    progress: bool = True,
) -> tuple[FLT, TrainResult]:
    """Our FLT variant (``cfg.variant``), trained as the thesis's is, from the same key:
    its step ``i`` sees the thesis FLT's episodes of step ``i`` (its own ``train_steps``)."""
    model = make_model(cfg.world, cfg.variant)
    return model, train(model, cfg.variant, cfg.world, system, key, progress, desc="FLT (ours)")


def run(cfg: FlowLeniaChapterConfig, key: jax.Array, progress: bool = True) -> Result:
    """The chapter from ``key``: the gallery, the system, the two ``P^0`` rules, the
    FLT's training, its held-out evaluation and diagnosis, and the surprise search
    (the notebook calls the same stages one by one, in this order, with these keys)."""
    world = cfg.world
    k_gallery, k_pick, k_train, k_eval, k_search = jax.random.split(key, 5)
    gallery = random_gallery(k_gallery, world, cfg.gallery_systems)
    criteria = SystemCriteria()
    choice = pick_system(k_pick, world, cfg.system_candidates, cfg.system_probes, criteria)
    p0 = compare_p0(choice, world, k_pick, cfg.system_probes, criteria.window)
    model = make_model(world, cfg.flt)
    trained = train(model, cfg.flt, world, choice.system, k_train, progress)
    args = (model, trained.params, world, choice.system, trained.mean_frames, k_eval)
    held_out = evaluate(*args, cfg.eval_episodes, cfg.eval_batch)
    diagnosis = diagnose(
        model,
        trained.params,
        trained.mean_frames,
        world,
        choice.system,
        k_eval,
        cfg.eval_batch,
        jax.random.fold_in(k_eval, 2),
    )
    variant = variant_held_out = None
    searched, searched_params = model, trained.params
    if cfg.variant is not None:
        v_model, variant = train_variant(cfg, choice.system, k_train, progress)
        variant_held_out = evaluate(
            v_model,
            variant.params,
            world,
            choice.system,
            variant.mean_frames,
            k_eval,
            cfg.eval_episodes,
            cfg.eval_batch,
        )
        if best_model(held_out, variant_held_out) == OUR_FLT:
            searched, searched_params = v_model, variant.params
    search = surprise_search(cfg, searched).run(
        searched_params, choice.system, k_search, cfg.search_iterations, cfg.search_chunk, progress
    )
    return Result(
        cfg,
        gallery,
        choice,
        p0,
        trained,
        held_out,
        diagnosis,
        search,
        variant,
        variant_held_out,
    )


def surprise_search(cfg: FlowLeniaChapterConfig, model: FLT) -> SurpriseSearch:
    """The chapter's ``SurpriseSearch`` (its batch, mutation and grid from ``cfg``)."""
    return SurpriseSearch(model, cfg.world, cfg.search_batch, cfg.search_sigma, cfg.search_bins)

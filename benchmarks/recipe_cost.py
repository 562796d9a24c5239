"""Seconds per training epoch of each recipe and aggregator on the default SynthCity, in one run.

Each job is built as ``python -m semvpr.train recipe=<r> aggregator=<a>`` builds it (no mask, the default
trunk, its features cached in ``--cache-dir``: the first run draws SynthCity's extra traversals and caches
the trunk features), and one training epoch runs through Lightning as in a job, validation left out:
recipe=triplet's epoch includes its descriptor-cache refresh and mining, recipe=gsv's its P × K batches
and the miner. Validation (the same for both recipes: the same place sets) is timed once per
aggregator beside it. ``--override`` applies Hydra overrides to every job (e.g.
``recipe.places_per_batch=16``).

    OMP_NUM_THREADS=1 python benchmarks/recipe_cost.py [--cache-dir outputs/cache] [--threads 1] \\
        [--recipes triplet gsv] [--aggregators netvlad gem mixvpr salad boq] [--override KEY=VALUE ...]

Prints one line per recipe · aggregator; last line: ``<recipe>·<aggregator>=<seconds>`` for every pair,
then ``<recipe>·<aggregator>/triplet·netvlad=<ratio>``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import lightning as L
import torch
from hydra import compose, initialize_config_dir

from semvpr.config.build import build_datamodule, build_retriever, init_aggregator, prepare
from semvpr.config.plan import job_plan, settings_of
from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import CONF_DIR
from semvpr.core.logs import quiet_third_party
from semvpr.core.precision import lightning_precision
from semvpr.retrieval.validation import RecallEvaluation

REFERENCE = "triplet·netvlad"


def job_config(cache_dir: Path, recipe: str, aggregator: str, overrides: list[str]):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(
            config_name="train",
            overrides=[f"recipe={recipe}", f"aggregator={aggregator}", f"paths.cache_dir={cache_dir}", *overrides],
        )


def epoch_seconds(cfg, job) -> tuple[float, float, dict]:
    """(seconds of one training epoch, seconds of one validation pass, what the epoch held)."""
    L.seed_everything(int(cfg.seed), verbose=False)
    settings = settings_of(cfg, training=True)
    retriever = build_retriever(settings, job.backbone, job.mask_source)
    init_aggregator(settings, retriever, job)
    datamodule = build_datamodule(settings, job.features, retriever.describe_store)
    trainer = L.Trainer(
        accelerator=str(cfg.trainer.accelerator),
        devices=1,
        precision=lightning_precision(str(cfg.trainer.precision), str(cfg.trainer.accelerator)),
        max_epochs=1,
        limit_val_batches=0,
        num_sanity_val_steps=0,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        reload_dataloaders_every_n_epochs=1,
    )
    tic = time.perf_counter()
    trainer.fit(retriever, datamodule)
    train_s = time.perf_counter() - tic
    evaluation = RecallEvaluation({"val": job.features["val"]}, retriever.describe_store)
    tic = time.perf_counter()
    evaluation.evaluate(job.features["val"])
    return train_s, time.perf_counter() - tic, {**datamodule.epoch_facts(), "steps": trainer.global_step}


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache-dir", type=Path, default=Path("outputs/cache"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--recipes", nargs="+", default=["triplet", "gsv"])
    ap.add_argument("--aggregators", nargs="+", default=["netvlad", "gem", "mixvpr", "salad", "boq"])
    ap.add_argument("--override", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    quiet_third_party()
    seconds: dict[str, float] = {}
    for recipe in args.recipes:
        first = job_config(args.cache_dir, recipe, args.aggregators[0], args.override)
        job = prepare(job_plan(first), {})
        for aggregator in args.aggregators:
            cfg = job_config(args.cache_dir, recipe, aggregator, args.override)
            train_s, val_s, facts = epoch_seconds(cfg, job)
            name = f"{recipe}·{aggregator}"
            seconds[name] = train_s
            held = {k: v for k, v in facts.items() if not isinstance(v, list)}
            if "tuples_per_epoch" in facts:
                held["tuples"] = facts["tuples_per_epoch"][-1] if facts["tuples_per_epoch"] else None
            versus = (
                f" ({train_s / seconds[f'triplet·{aggregator}']:.2f}x triplet·{aggregator})"
                if recipe != "triplet" and f"triplet·{aggregator}" in seconds
                else ""
            )
            print(f"{name}: epoch {train_s:.2f} s{versus}, val {val_s:.2f} s, {held}", flush=True)
    pairs = " ".join(f"{n}={s:.2f}" for n, s in seconds.items())
    ratios = (
        " ".join(f"{n}/{REFERENCE}={s / seconds[REFERENCE]:.2f}" for n, s in seconds.items())
        if REFERENCE in seconds
        else ""
    )
    print(f"{pairs} {ratios}".strip())


if __name__ == "__main__":
    main()

"""results.csv and hits.npz of the espnetv2-trained-streets sweeps (run.sh OUT).

results.csv: per pair, model and condition (no mask, ESPNetv2's mask in place of the model's own, its controls),
Recall@1/5/10 as mean and sample std over the training seeds, and the R@1 gain over the same checkpoints without a
mask with its 95 % interval (a bootstrap that resamples the seeds and, jointly for them, the queries); then the
contrasts stated before the runs, each pooled over the three pairs (frame i is the same place in every traversal,
so a place's gains are averaged over the pairs and the places resampled once) and, where it says so, over the four
models, its interval corrected for the eight claims together (Bonferroni). Then the occluded pair (``OUT/occluded``):
each condition on its occluded frames against the same checkpoints on them without a mask (and that against its
frames as they are), and its four contrasts pooled over the four models, corrected for those four together.

hits.npz: every evaluation's per-query hits at N = 1, 5, 10, 20 (``<pair>|<filter>|<seed>|<condition>``).

    python experiments/espnetv2-trained-streets/summarize.py OUT
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.reporting.evaluations import Evaluation, read_evaluations, summary_input, write_summary
from semvpr.reporting.paired import LEVEL, corrected_level, seeds_and_queries_gain

PAIRS = ("day_left-night_right", "day_right-night_right", "day_left-day_right")
MODELS = {
    "none": "NetVLAD (filter=none)",
    "attention": "SRAL (filter=attention)",
    "unet": "SRAL + SynthCity student (filter=unet)",
    "mask2former": "SRAL + SynthCity teacher (filter=mask2former)",
}
#: Each condition: the sweep run.sh writes it into, what its jobs' eval.json record, and its label.
CONDITIONS = {
    "none": ("none", {"mask": "none"}, "none"),
    "espnetv2": ("espnetv2", {"mask": "teacher", "mask_control": "none"}, "ESPNetv2 mask"),
    "objects": ("espnetv2", {"mask_control": "objects"}, "its objects only (sky kept)"),
    "sky": ("espnetv2", {"mask_control": "sky"}, "its sky only"),
    "random": ("drawn", {"mask_control": "random"}, "as many cells at random"),
    "shuffled": ("drawn", {"mask_control": "shuffled"}, "another image's mask"),
}
#: The occluded pair's conditions, in ``OUT/occluded/<pair>``, and each one's reference.
OCCLUDED = {
    "occluded": ("none", {"mask": "none"}, "occluded, no mask"),
    "oracle": ("none", {"mask": "oracle"}, "occluded, the pasted pixels' mask"),
    "occluded-espnetv2": ("espnetv2", {"mask": "teacher", "mask_control": "none"}, "occluded, ESPNetv2 mask"),
    "occluded-random": ("espnetv2", {"mask_control": "random"}, "occluded, as many cells at random"),
}
REFERENCE = {"occluded": "none", "oracle": "occluded", "occluded-espnetv2": "occluded", "occluded-random": "occluded"}
#: The contrasts claimed, stated before the runs: (condition, reference, the models pooled, label).
CONTRASTS = (
    ("espnetv2", "none", ("none",), "NetVLAD: ESPNetv2 mask − none"),
    ("espnetv2", "none", ("attention",), "SRAL: ESPNetv2 mask − none"),
    ("espnetv2", "none", ("unet",), "SRAL + SynthCity student: ESPNetv2 mask − none"),
    ("espnetv2", "none", ("mask2former",), "SRAL + SynthCity teacher: ESPNetv2 mask − none"),
    ("objects", "none", tuple(MODELS), "all four: objects only − none"),
    ("sky", "none", tuple(MODELS), "all four: sky only − none"),
    ("espnetv2", "random", tuple(MODELS), "all four: ESPNetv2 mask − random cells"),
    ("espnetv2", "shuffled", tuple(MODELS), "all four: ESPNetv2 mask − another image's mask"),
)
#: The occluded pair's contrasts (one family of their own), pooled over the four models.
OCCLUDED_CONTRASTS = (
    ("occluded", "none", tuple(MODELS), "all four, occluded: occlusion's cost (occluded − as they are)"),
    ("oracle", "occluded", tuple(MODELS), "all four, occluded: pasted pixels' mask − none"),
    ("occluded-espnetv2", "occluded", tuple(MODELS), "all four, occluded: ESPNetv2 mask − none"),
    ("occluded-espnetv2", "occluded-random", tuple(MODELS), "all four, occluded: ESPNetv2 mask − random cells"),
)
FIELDS = (
    "pair", "model", "mask", "seeds", "R@1_mean", "R@1_std", "R@5_mean", "R@10_mean",
    "gain", "ci_low", "ci_high", "excludes_0", "level",
)  # fmt: skip
_JOB = re.compile(r"filter=(?P<filter>[a-z0-9]+),seed=(?P<seed>\d+)")


def trained_as(evaluation: Evaluation) -> tuple[str, int]:
    """The filter and training seed of the checkpoint an evaluation read, from its training job's directory."""
    found = _JOB.search(Path(str(evaluation.result.get("checkpoint"))).parent.parent.name)
    if found is None or found["filter"] not in MODELS:
        raise SemvprError(
            f"{evaluation.dir}: its checkpoint is not one of run.sh's: {evaluation.result.get('checkpoint')}"
        )
    return found["filter"], int(found["seed"])


def sweep_hits(folder: Path, condition: str) -> dict[tuple[str, int], Evaluation]:
    """The jobs of one condition in one pair's folder by (filter, training seed)."""
    sweep, recorded, _ = {**CONDITIONS, **OCCLUDED}[condition]
    jobs: dict[tuple[str, int], Evaluation] = {}
    for e in read_evaluations(folder / sweep):
        if all(e.result.get(k) == v for k, v in recorded.items()):
            key = trained_as(e)
            if key in jobs:
                raise SemvprError(f"{folder / sweep}: two {condition} evaluations of {key}; rerun run.sh")
            jobs[key] = e
    if not jobs:
        raise SemvprError(f"{folder / sweep}: no {condition} evaluation; rerun run.sh")
    return jobs


def _row(pair: str, model: str, mask: str, **values: object) -> dict[str, object]:
    return {"pair": pair, "model": model, "mask": mask, **values}


def pooled(
    r1: dict[tuple[str, str, str], np.ndarray], pairs: tuple[str, ...], contrasts: tuple, seeds: int
) -> list[dict[str, object]]:
    """One row per contrast (condition, reference, models, label), pooled over ``pairs`` and the models named (a
    place's per-seed gains averaged over them: one (seeds, places) set), corrected for the contrasts together."""
    level = round(corrected_level(len(contrasts)), 4)
    rows = []
    for condition, reference, models, label in contrasts:
        diff = np.mean([r1[(p, m, condition)].astype(float) - r1[(p, m, reference)] for p in pairs for m in models], 0)
        gain = seeds_and_queries_gain([diff], level=level)
        rows.append(_row("all three" if len(pairs) > 1 else pairs[0].replace("-", " → "), "pooled", label,
                         seeds=seeds, **gain.record(level)))  # fmt: skip
    return rows


@exit_on_user_error
def main() -> None:
    out = summary_input(__doc__.splitlines()[0], "experiments/espnetv2-trained-streets/run.sh")
    occluded_pairs = sorted(p.name for p in (out / "occluded").glob("*") if p.is_dir())
    if len(occluded_pairs) != 1 or occluded_pairs[0] not in PAIRS:
        raise SemvprError(f"{out / 'occluded'}: one occluded pair expected, found {occluded_pairs}; rerun run.sh")
    occluded_pair = occluded_pairs[0]
    jobs = {(pair, c): sweep_hits(out / pair, c) for pair in PAIRS for c in CONDITIONS}
    jobs |= {(occluded_pair, c): sweep_hits(out / "occluded" / occluded_pair, c) for c in OCCLUDED}
    seeds = sorted({s for f, s in jobs[(PAIRS[0], "none")]})
    for (pair, condition), found in jobs.items():
        if set(found) != {(f, s) for f in MODELS for s in seeds}:
            raise SemvprError(
                f"{out / pair}: {condition} evaluations of {sorted(found)}, expected seeds {seeds} of each"
            )
    # (pair, filter, condition): a (seeds, queries) array of R@1 hits.
    r1 = {(p, f, c): np.stack([jobs[(p, c)][(f, s)].r1 for s in seeds]) for p, c in jobs for f in MODELS}
    rows: list[dict[str, object]] = []
    saved: dict[str, np.ndarray] = {}
    parts = [(pair, CONDITIONS, lambda c: "none") for pair in PAIRS] + [(occluded_pair, OCCLUDED, REFERENCE.get)]
    for pair, conditions, reference_of in parts:
        for filter_, model in MODELS.items():
            for condition, (_, _, label) in conditions.items():
                results = [jobs[(pair, condition)][(filter_, s)] for s in seeds]
                for s, e in zip(seeds, results, strict=True):
                    saved[f"{pair}|{filter_}|{s}|{condition}"] = e.hits
                recalls = {n: np.array([e.result[f"test/R@{n}"] for e in results]) for n in (1, 5, 10)}
                row = _row(pair.replace("-", " → "), model, label, seeds=len(seeds))
                row |= {
                    "R@1_mean": round(float(recalls[1].mean()), 2),
                    "R@1_std": round(float(recalls[1].std(ddof=1)), 2),
                }
                row |= {f"R@{n}_mean": round(float(recalls[n].mean()), 2) for n in (5, 10)}
                if condition != "none":
                    reference = reference_of(condition)
                    diff = r1[(pair, filter_, condition)].astype(float) - r1[(pair, filter_, reference)]
                    row |= seeds_and_queries_gain([diff], level=LEVEL).record(LEVEL)
                rows.append(row)
    rows += pooled(r1, PAIRS, CONTRASTS, len(seeds))
    rows += pooled(r1, (occluded_pair,), OCCLUDED_CONTRASTS, len(seeds))
    write_summary(Path(__file__).parent, FIELDS, rows, saved)


if __name__ == "__main__":
    main()

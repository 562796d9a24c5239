"""results.csv and hits.npz of the espnetv2-trained-streets sweeps (run.sh OUT).

results.csv: per pair, model and condition (no mask, ESPNetv2's mask in place of the model's own, its controls),
Recall@1/5/10 as mean and sample std over the training seeds, and the R@1 gain over the same checkpoints without a
mask with its 95 % interval (a bootstrap that resamples the seeds and, jointly for them, the queries); then the
contrasts stated before the runs, each pooled over the three pairs (frame i is the same place in every traversal,
so a place's gains are averaged over the pairs and the places resampled once) and, where it says so, over the four
models, its interval corrected for the eight claims together (Bonferroni). Then the occluded pair, at CamVid train's
coverage (``OUT/occluded``) and at 10 % of each image (``OUT/occluded-10``): each condition on the occluded frames
against the same checkpoints on them without a mask (and that against its frames as they are), and, per level, its
four contrasts pooled over the four models, corrected for those four together.

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
#: The occluded frames of one pair, by the folder run.sh writes them into (``OUT/<folder>/<pair>``): the label's
#: words and the condition names' suffix. CamVid train's coverage first; then a fixed 10 % of each image's pixels.
OCCLUSIONS = {"occluded": ("occluded", ""), "occluded-10": ("occluded 10 %", "-10")}


def occluded_conditions(tag: str, suffix: str) -> dict[str, tuple[str, dict[str, str], str]]:
    """One occlusion's conditions: sweep, what its jobs' eval.json record, label."""
    return {
        f"occluded{suffix}": ("none", {"mask": "none"}, f"{tag}, no mask"),
        f"oracle{suffix}": ("none", {"mask": "oracle"}, f"{tag}, the pasted pixels' mask"),
        f"occluded{suffix}-espnetv2": (
            "espnetv2",
            {"mask": "teacher", "mask_control": "none"},
            f"{tag}, ESPNetv2 mask",
        ),
        f"occluded{suffix}-random": ("espnetv2", {"mask_control": "random"}, f"{tag}, as many cells at random"),
    }


def occluded_contrasts(tag: str, suffix: str) -> tuple[tuple[str, str, tuple[str, ...], str], ...]:
    """One occlusion's four contrasts (a family of their own), pooled over the four models."""
    o = f"occluded{suffix}"
    return (
        (o, "none", tuple(MODELS), f"all four, {tag}: occlusion's cost (occluded − as they are)"),
        (f"oracle{suffix}", o, tuple(MODELS), f"all four, {tag}: pasted pixels' mask − none"),
        (f"{o}-espnetv2", o, tuple(MODELS), f"all four, {tag}: ESPNetv2 mask − none"),
        (f"{o}-espnetv2", f"{o}-random", tuple(MODELS), f"all four, {tag}: ESPNetv2 mask − random cells"),
    )


OCCLUDED = {folder: occluded_conditions(*words) for folder, words in OCCLUSIONS.items()}
#: Every condition of every folder: (sweep, recorded, label).
ALL_CONDITIONS = {**CONDITIONS, **{c: v for level in OCCLUDED.values() for c, v in level.items()}}
#: Each occluded condition's reference: the frames as they are for those without a mask (each level's first), those
#: for every mask on them.
REFERENCE = {c: "none" if i == 0 else next(iter(level)) for level in OCCLUDED.values() for i, c in enumerate(level)}
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
    sweep, recorded, _ = ALL_CONDITIONS[condition]
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
    occluded_pairs = {f: sorted(p.name for p in (out / f).glob("*") if p.is_dir()) for f in OCCLUSIONS}
    if (
        any(len(found) != 1 or found[0] not in PAIRS for found in occluded_pairs.values())
        or len({found[0] for found in occluded_pairs.values()}) != 1
    ):
        raise SemvprError(f"{out}: one occluded pair expected, the same in {' and '.join(OCCLUSIONS)}, found "
                          f"{occluded_pairs}; rerun run.sh")  # fmt: skip
    occluded_pair = occluded_pairs["occluded"][0]
    jobs = {(pair, c): sweep_hits(out / pair, c) for pair in PAIRS for c in CONDITIONS}
    for folder, conditions in OCCLUDED.items():
        jobs |= {(occluded_pair, c): sweep_hits(out / folder / occluded_pair, c) for c in conditions}
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
    parts = [(pair, CONDITIONS, lambda c: "none") for pair in PAIRS]
    parts += [(occluded_pair, conditions, REFERENCE.get) for conditions in OCCLUDED.values()]
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
    for words in OCCLUSIONS.values():
        rows += pooled(r1, (occluded_pair,), occluded_contrasts(*words), len(seeds))
    write_summary(Path(__file__).parent, FIELDS, rows, saved)


if __name__ == "__main__":
    main()

"""results.csv and hits.npz of the synthcity-training-controls sweeps (run.sh OUT).

Per training seed and city draw, SRAL trained and tested without a mask (``filter=attention``), with the student's
mask (``unet``), and with that mask's two content controls in place of it at training and test alike (as many cells
removed at random, ``mask.control=random``; another image's mask, ``shuffled``). Every evaluation is checked against
its training run's test R@1.

The contrasts, stated before the runs: the student's mask over each control, each as trained (does the content of
the mask matter once the model learns with what it is given, or only how much it removes), and each control over
SRAL without a mask (does removing that much of the image help by itself). Each pooled over every seed and draw,
the draws weighted alike, its interval resampling the training seeds and, jointly for them, the test queries within
each draw (``reporting.paired.seeds_and_queries_gain``), corrected for the four claims together (Bonferroni).

results.csv: per seed and draw, each model's test R@1; then its mean over the cells, and each contrast pooled,
with its interval. hits.npz: every evaluation's per-query hits at N = 1, 5, 10, 20 (``seed=S,draw=D|<model>``).

    python experiments/synthcity-training-controls/summarize.py OUT [--seeds 3] [--draws 3]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from semvpr.core import machine
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import read_json
from semvpr.reporting.evaluations import read_evaluations, write_summary
from semvpr.reporting.paired import LEVEL, corrected_level, seeds_and_queries_gain

HERE = Path(__file__).parent
#: Each model: what its evaluation's eval.json records (the mask and its control, from the checkpoint), its label.
MODELS = {
    "none": ({"mask": "none"}, "SRAL, no mask"),
    "mask": ({"mask": "student", "mask_control": "none"}, "the student's mask"),
    "random": ({"mask": "student", "mask_control": "random"}, "as many cells at random, as trained"),
    "shuffled": ({"mask": "student", "mask_control": "shuffled"}, "another image's mask, as trained"),
}
#: The contrasts claimed, stated before the runs: (model, reference, label).
CONTRASTS = (
    ("mask", "random", "mask − random cells, each as trained"),
    ("mask", "shuffled", "mask − another image's mask, each as trained"),
    ("random", "none", "random cells as trained − none"),
    ("shuffled", "none", "another image's mask as trained − none"),
)
FIELDS = ("draw", "seed", "model", "R@1", "gain", "ci_low", "ci_high", "excludes_0", "level", "machine")


def cell_hits(out: Path, name: str) -> dict[str, np.ndarray]:
    """One cell's hits by model, each evaluation checked against its training run's test R@1 and every model
    present once."""
    hits: dict[str, np.ndarray] = {}
    for evaluation in read_evaluations(out / "test" / name):
        result = evaluation.result
        run = Path(str(result["checkpoint"])).parents[1]
        if run.parents[1] != out / "train" / name:
            raise SemvprError(f"{evaluation.dir}: evaluates {run}, not a run of {out / 'train' / name}")
        found = [m for m, (recorded, _) in MODELS.items() if all(result.get(k) == v for k, v in recorded.items())]
        if len(found) != 1 or found[0] in hits:
            raise SemvprError(f"{evaluation.dir}: not one of run.sh's evaluations of {name}; rerun run.sh")
        trained = read_json(run / "metrics.json", "training metrics")["test/R@1"]
        if abs(trained - result["test/R@1"]) > 0.006:
            raise SemvprError(f"{evaluation.dir}: R@1 {result['test/R@1']} where its run tested {trained}")
        hits[found[0]] = evaluation.hits
    if set(hits) != set(MODELS):
        raise SemvprError(f"{out / 'test' / name}: missing {sorted(set(MODELS) - set(hits))}; rerun run.sh")
    return hits


@exit_on_user_error
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the folder run.sh wrote")
    parser.add_argument("--seeds", type=int, default=3, help="training seeds (run.sh's SEEDS)")
    parser.add_argument("--draws", type=int, default=3, help="city draws (run.sh's DRAWS)")
    args = parser.parse_args()
    cells = {(s, d): f"seed={s},draw={d}" for d in range(args.draws) for s in range(args.seeds)}
    unfinished = [n for n in cells.values() if not (args.out / "test" / n / "results.md").is_file()]
    if unfinished:
        raise SemvprError(f"{args.out}: {len(unfinished)} of {len(cells)} cells not finished ({unfinished[0]}, ...)")
    ran_on = machine.short_name(machine.describe())  # run.sh runs where it summarises
    level = corrected_level(len(CONTRASTS))
    rows: list[dict[str, object]] = []
    saved: dict[str, np.ndarray] = {}
    diffs: dict[str, dict[int, list[np.ndarray]]] = {}
    for (seed, draw), name in cells.items():
        hits = cell_hits(args.out, name)
        for model, h in hits.items():
            saved[f"{name}|{model}"] = h
            rows.append({"draw": draw, "seed": seed, "model": MODELS[model][1], "R@1": round(100 * h[:, 0].mean(), 2),
                         "machine": ran_on})  # fmt: skip
        for model, reference, label in CONTRASTS:
            gain = hits[model][:, 0].astype(float) - hits[reference][:, 0]
            diffs.setdefault(label, {}).setdefault(draw, []).append(gain)
    for _, label in MODELS.values():
        r1 = [float(r["R@1"]) for r in rows if r["model"] == label]
        rows.append(
            {"draw": "all", "seed": f"mean of {len(r1)} cells", "model": label, "R@1": round(float(np.mean(r1)), 2)}
        )
    for label, by_draw in diffs.items():
        pooled = seeds_and_queries_gain([np.stack(sets) for sets in by_draw.values()], level=level)
        rows.append({"draw": "all", "seed": f"{len(cells)} cells", "model": label, **pooled.record(level)})
        print(f"{label}: {pooled.text()} R@1 ({LEVEL:.0%} family-wise, {level:.2%} each)")
    write_summary(HERE, FIELDS, rows, saved)


if __name__ == "__main__":
    main()

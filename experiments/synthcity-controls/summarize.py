"""results.csv and hits.npz of the synthcity-controls sweeps (run.sh OUT).

Per training seed and city draw, SRAL without a mask (``filter=attention``) and SRAL with the student's mask
(``unet``) and the teacher's (``mask2former``), each masked checkpoint evaluated with its own mask and with the
mask's controls (``semvpr/retrieval/controls.py``). Every evaluation of a checkpoint with its own mask is checked
against its training run's test R@1.

The contrasts, stated before the runs, for each mask source: the mask over SRAL without one (does the mask help
here, as synthcity-power measured with 15 seeds), the mask over its two content controls on the same checkpoint
(as many cells removed at random; another image's mask: does the content of the mask matter, or only its area),
and each class control and each side over SRAL without a mask (the objects only, the sky kept; the sky only;
the mask on the database alone; on the queries alone). Each pooled over every seed and draw, the draws weighted
alike, its interval resampling the training seeds and, jointly for them, the test queries within each draw
(``reporting.paired.seeds_and_queries_gain``), corrected for all the claims together (Bonferroni).

results.csv: per seed and draw, each source's R@1 under every condition; then its mean over the cells, and each
contrast pooled, with its interval. hits.npz: every evaluation's per-query hits at N = 1, 5, 10, 20
(``seed=S,draw=D|<source>|<condition>``).

    python experiments/synthcity-controls/summarize.py OUT [--seeds 3] [--draws 3]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from semvpr.core import machine
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import read_json
from semvpr.reporting.evaluations import Evaluation, read_evaluations, write_summary
from semvpr.reporting.paired import LEVEL, corrected_level, seeds_and_queries_gain

HERE = Path(__file__).parent
#: The training filter of each mask source, and of the reference without a mask.
FILTERS = {"none": "attention", "student": "unet", "teacher": "mask2former"}
SOURCES = ("student", "teacher")
#: Each condition of a masked checkpoint: the sweep run.sh writes it into, what its jobs' eval.json record, and
#: its label.
CONDITIONS = {
    "mask": ("own", {"mask_control": "none", "mask_apply": "both"}, "its own mask"),
    "objects": ("classes", {"mask_control": "objects", "mask_apply": "both"}, "its objects only (sky kept)"),
    "sky": ("classes", {"mask_control": "sky", "mask_apply": "both"}, "its sky only"),
    "random": ("drawn", {"mask_control": "random", "mask_apply": "both"}, "as many cells at random"),
    "shuffled": ("drawn", {"mask_control": "shuffled", "mask_apply": "both"}, "another image's mask"),
    "database": ("sides", {"mask_control": "none", "mask_apply": "database"}, "on the database only"),
    "queries": ("sides", {"mask_control": "none", "mask_apply": "queries"}, "on the queries only"),
}
#: The contrasts claimed for each source, stated before the runs: (condition, reference, label); the reference
#: "none" is SRAL without a mask, any other a condition of the same checkpoint.
CONTRASTS = (
    ("mask", "none", "mask − none"),
    ("mask", "random", "mask − random cells"),
    ("mask", "shuffled", "mask − another image's mask"),
    ("objects", "none", "objects only − none"),
    ("sky", "none", "sky only − none"),
    ("database", "none", "database only − none"),
    ("queries", "none", "queries only − none"),
)
FIELDS = ("draw", "seed", "source", "condition", "R@1", "gain", "ci_low", "ci_high", "excludes_0", "level", "machine")


def _trained_on(evaluation: Evaluation, train: Path) -> tuple[str, Path]:
    """The mask source an evaluation's checkpoint was trained with (its filter) and its run, checked to be a run of
    ``train``."""
    run = Path(str(evaluation.result["checkpoint"])).parents[1]
    for mask, filter_name in FILTERS.items():
        if run.parent == train and f"filter={filter_name}" in run.name:
            return mask, run
    raise SemvprError(f"{evaluation.dir}: evaluates {run}, not a run of {train}")


def _key(source: str, sweep: str, result: dict) -> tuple[str, str] | None:
    """The (source, condition) an evaluation of a checkpoint trained with ``source`` is, None where run.sh makes
    no such evaluation."""
    if source == "none":
        return ("none", "none") if sweep == "own" and result["mask"] == "none" else None
    if result["mask"] != source:
        return None
    for condition, (in_sweep, recorded, _) in CONDITIONS.items():
        if in_sweep == sweep and all(result[k] == v for k, v in recorded.items()):
            return source, condition
    return None


def cell_hits(out: Path, name: str) -> dict[tuple[str, str], np.ndarray]:
    """One cell's hits by (source, condition), ``("none", "none")`` for SRAL without a mask, each own-mask
    evaluation checked against its training run's test R@1 and every condition present once."""
    train, hits = out / "train" / name, {}
    for sweep in sorted({s for s, _, _ in CONDITIONS.values()}):
        for evaluation in read_evaluations(out / "test" / name / sweep):
            (source, run), result = _trained_on(evaluation, train), evaluation.result
            key = _key(source, sweep, result)
            if key is None or key in hits:
                raise SemvprError(f"{evaluation.dir}: not one of run.sh's evaluations of {name}; rerun run.sh")
            if sweep == "own":
                trained = read_json(run / "metrics.json", "training metrics")["test/R@1"]
                if abs(trained - result["test/R@1"]) > 0.006:
                    raise SemvprError(f"{evaluation.dir}: R@1 {result['test/R@1']} where its run tested {trained}")
            hits[key] = evaluation.hits
    wanted = {("none", "none")} | {(s, c) for s in SOURCES for c in CONDITIONS}
    if set(hits) != wanted:
        raise SemvprError(f"{out / 'test' / name}: missing {sorted(wanted - set(hits))}; rerun run.sh")
    return hits


@exit_on_user_error
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the folder run.sh wrote")
    parser.add_argument("--seeds", type=int, default=3, help="training seeds (run.sh's SEEDS)")
    parser.add_argument("--draws", type=int, default=3, help="city draws (run.sh's DRAWS)")
    args = parser.parse_args()
    if not (args.out / "test").is_dir():
        raise SemvprError(f"{args.out} holds no evaluation sweeps (bash experiments/synthcity-controls/run.sh OUT)")
    cells = {(s, d): f"seed={s},draw={d}" for s in range(args.seeds) for d in range(args.draws)}
    unfinished = [n for n in cells.values() if not (args.out / "test" / n / "sides" / "results.md").is_file()]
    if unfinished:
        raise SemvprError(f"{args.out}: {len(unfinished)} of {len(cells)} cells not finished ({unfinished[0]}, ...)")
    ran_on = machine.short_name(machine.describe())  # run.sh runs where it summarises
    level = corrected_level(len(CONTRASTS) * len(SOURCES))
    rows: list[dict[str, object]] = []
    saved: dict[str, np.ndarray] = {}
    diffs: dict[tuple[str, str], dict[int, list[np.ndarray]]] = {}
    for (seed, draw), name in sorted(cells.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        hits = cell_hits(args.out, name)
        for (source, condition), h in hits.items():
            saved[f"{name}|{source}|{condition}"] = h
            rows.append({"draw": draw, "seed": seed, "source": source, "condition": condition,
                         "R@1": round(100 * h[:, 0].mean(), 2), "machine": ran_on})  # fmt: skip
        for source in SOURCES:
            for condition, reference, label in CONTRASTS:
                ref = hits["none", "none"] if reference == "none" else hits[source, reference]
                gain = hits[source, condition][:, 0].astype(float) - ref[:, 0]
                diffs.setdefault((source, label), {}).setdefault(draw, []).append(gain)
    for source, condition in [("none", "none"), *((s, c) for s in SOURCES for c in CONDITIONS)]:
        r1 = [float(r["R@1"]) for r in rows if (r["source"], r["condition"]) == (source, condition)]
        label = "no mask" if source == "none" else CONDITIONS[condition][2]
        rows.append({"draw": "all", "seed": f"mean of {len(r1)} cells", "source": source, "condition": label,
                     "R@1": round(float(np.mean(r1)), 2)})  # fmt: skip
    for (source, label), by_draw in diffs.items():
        pooled = seeds_and_queries_gain([np.stack(sets) for sets in by_draw.values()], level=level)
        rows.append({"draw": "all", "seed": f"{len(cells)} cells", "source": source, "condition": label,
                     **pooled.record(level)})  # fmt: skip
        print(f"{source}'s {label}: {pooled.text()} R@1 ({LEVEL:.0%} family-wise, {level:.2%} each)")
    write_summary(HERE, FIELDS, rows, saved)


if __name__ == "__main__":
    main()

"""results.csv and hits.npz of the espnetv2-streets sweeps (run.sh OUT).

results.csv: per pair, model and condition (no mask, ESPNetv2's mask, and its controls), Recall@1/5/10 and the
R@1 gain over the same model without a mask, paired by query, with its 95 % bootstrap interval (random and
shuffled: each query's hits averaged over the three control seeds); then the contrasts stated before the runs,
each pooled over the three pairs and both models with the places resampled jointly (frame i is the same place in
every traversal) and its interval corrected for the seven claims together (Bonferroni). Where run.sh was given
the CamVid-distilled student (a ``student`` sweep in every pair), its mask too, with its two contrasts a family of
their own (corrected for the two).

hits.npz: every evaluation's per-query hits at N = 1, 5, 10, 20 (``<pair>|<aggregator>|<condition>|<seed>``).

    python experiments/espnetv2-streets/summarize.py OUT
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.reporting.evaluations import read_evaluations, summary_input, write_summary
from semvpr.reporting.paired import LEVEL, corrected_level, paired_gain, pooled_gain

PAIRS = ("day_left-night_right", "day_right-night_right", "day_left-day_right")
MODELS = {"gem": "no VPR training: GeM (p = 3)", "netvlad": "no VPR training: NetVLAD (k-means on SynthCity)"}
SEEDS = (0, 1, 2)
#: Each condition: the sweep run.sh writes it into, what its jobs' eval.json record, the seeds it is drawn over,
#: and its label.
CONDITIONS = {
    "none": ("masks", {"mask": "none"}, (0,), "none"),
    "mask": ("masks", {"mask": "teacher", "mask_control": "none", "mask_apply": "both"}, (0,), "ESPNetv2 mask"),
    "objects": ("classes", {"mask_control": "objects"}, (0,), "its objects only (sky kept)"),
    "sky": ("classes", {"mask_control": "sky"}, (0,), "its sky only"),
    "random": ("drawn", {"mask_control": "random"}, SEEDS, "as many cells at random (3 seeds)"),
    "shuffled": ("drawn", {"mask_control": "shuffled"}, SEEDS, "another image's mask (3 seeds)"),
    "database": ("sides", {"mask_apply": "database"}, (0,), "on the database only"),
    "queries": ("sides", {"mask_apply": "queries"}, (0,), "on the queries only"),
}
#: The student's mask, where run.sh ran it: ESPNetv2's labels of CamVid train distilled into the U-Net student.
STUDENT = {"student": ("student", {"mask": "student"}, (0,), "its CamVid-distilled student's mask")}
#: The contrasts claimed, stated before the runs: (condition, reference, label).
CONTRASTS = (
    ("mask", "none", "ESPNetv2 mask − none"),
    ("objects", "none", "objects only − none"),
    ("sky", "none", "sky only − none"),
    ("mask", "random", "ESPNetv2 mask − random cells"),
    ("mask", "shuffled", "ESPNetv2 mask − another image's mask"),
    ("database", "none", "database only − none"),
    ("queries", "none", "queries only − none"),
)
#: The student's contrasts, stated before its runs: a family of their own.
STUDENT_CONTRASTS = (
    ("student", "none", "student's mask − none"),
    ("student", "mask", "student's mask − ESPNetv2 mask"),
)
FIELDS = ("pair", "model", "mask", "R@1", "R@5", "R@10", "gain", "ci_low", "ci_high", "excludes_0", "level")


def sweep_hits(folder: Path, condition: str, entry: tuple) -> dict[tuple[str, int], tuple[dict, np.ndarray]]:
    """The jobs of one condition (its :data:`CONDITIONS` entry) in one pair's folder by (aggregator, control seed):
    eval.json and hits (``reporting.evaluations``), checked against the jobs run.sh gives the condition."""
    sweep, recorded, seeds, _ = entry
    jobs = {
        (e.result["aggregator"], int(e.result["mask_control_seed"]) if len(seeds) > 1 else 0): (e.result, e.hits)
        for e in read_evaluations(folder / sweep)
        if all(e.result.get(k) == v for k, v in recorded.items())
    }
    wanted = {(a, s) for a in MODELS for s in seeds}
    if set(jobs) != wanted:
        raise SemvprError(f"{folder / sweep}: {condition} jobs {sorted(jobs)}, expected {sorted(wanted)}; rerun run.sh")
    return jobs


def _row(pair: str, model: str, mask: str, **values: object) -> dict[str, object]:
    return {"pair": pair, "model": model, "mask": mask, **values}


@exit_on_user_error
def main() -> None:
    out = summary_input(__doc__.splitlines()[0], "experiments/espnetv2-streets/run.sh")
    rows: list[dict[str, object]] = []
    saved: dict[str, np.ndarray] = {}
    rates: dict[tuple[str, str, str], np.ndarray] = {}  # (pair, aggregator, condition): each query's R@1 rate
    student = all((out / pair / "student").is_dir() for pair in PAIRS)
    conditions = CONDITIONS | (STUDENT if student else {})
    for pair in PAIRS:
        jobs = {condition: sweep_hits(out / pair, condition, entry) for condition, entry in conditions.items()}
        for aggregator, model in MODELS.items():
            for condition, (_, _, seeds, label) in conditions.items():
                drawn = [jobs[condition][(aggregator, seed)] for seed in seeds]
                for seed, (_, hits) in zip(seeds, drawn, strict=True):
                    saved[f"{pair}|{aggregator}|{condition}|{seed}"] = hits
                rates[(pair, aggregator, condition)] = np.mean([hits[:, 0] for _, hits in drawn], axis=0)
                recalls = {f"R@{n}": round(float(np.mean([r[f"test/R@{n}"] for r, _ in drawn])), 2) for n in (1, 5, 10)}
                row = _row(pair.replace("-", " → "), model, label, **recalls)
                if condition != "none":
                    gain = paired_gain(rates[(pair, aggregator, condition)], rates[(pair, aggregator, "none")])
                    row |= gain.record(LEVEL)
                rows.append(row)
    keys = [(p, a) for p in PAIRS for a in MODELS]
    for family in (CONTRASTS, STUDENT_CONTRASTS) if student else (CONTRASTS,):
        level = round(corrected_level(len(family)), 4)
        for condition, reference, label in family:
            gain = pooled_gain([(rates[(*k, condition)], rates[(*k, reference)]) for k in keys], level=level)
            rows.append(_row("all three", "both", label, **gain.record(level)))
    write_summary(Path(__file__).parent, FIELDS, rows, saved)


if __name__ == "__main__":
    main()

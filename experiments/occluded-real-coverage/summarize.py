"""results.csv and hits.npz of the occluded-real-coverage sweeps (run.sh OUT).

results.csv: per pair, model and condition, Recall@1/5/10 (occluded conditions: the mean over the three occluder
draws) and the R@1 difference from the condition's reference (the frames as they are for the occluded frames
without a mask; the occluded frames without a mask for each mask; its control for a mask against its control),
paired by query on the same draw, with its 95 % bootstrap interval (each query's difference averaged over the
draws); then the contrasts stated before the runs, each pooled over the pairs run (``PAIRS`` of run.sh) and
both models with the places resampled jointly, their intervals corrected for the seven claims together (Bonferroni).

hits.npz: every evaluation's per-query hits at N = 1, 5, 10, 20 (``<pair>|<aggregator>|<condition>|<draw>``).

    python experiments/occluded-real-coverage/summarize.py OUT
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import read_json, write_json
from semvpr.reporting.evaluations import read_evaluations, summary_input, write_summary
from semvpr.reporting.paired import LEVEL, corrected_level, paired_gain, pooled_gain

PAIRS = ("day_left-night_right", "day_right-night_right", "day_left-day_right")
MODELS = {"gem": "no VPR training: GeM (p = 3)", "netvlad": "no VPR training: NetVLAD (k-means on SynthCity)"}
DRAWS = (0, 1, 2)
#: Each condition: its sweep in run.sh, what its jobs' eval.json record, and its label.
CONDITIONS = {
    "clean": ("clean", {"mask": "none"}, "the frames as they are, no mask"),
    "occluded": ("occluded", {"mask": "none"}, "occluded, no mask"),
    "oracle": ("occluded", {"mask": "oracle"}, "occluded, the pasted pixels' mask"),
    "oracle-random": ("oracle-controls", {"mask_control": "random"}, "occluded, as many cells at random"),
    "oracle-shuffled": ("oracle-controls", {"mask_control": "shuffled"}, "occluded, another image's pasted mask"),
    "espnetv2": ("espnetv2", {"mask_control": "none"}, "occluded, ESPNetv2's mask"),
    "espnetv2-objects": ("espnetv2-controls", {"mask_control": "objects"}, "occluded, ESPNetv2's objects only"),
    "espnetv2-random": ("espnetv2-controls", {"mask_control": "random"}, "occluded, as many cells as ESPNetv2's"),
}
#: Each condition's reference in the per-comparison rows.
REFERENCE = {"occluded": "clean", "oracle-random": "oracle", "oracle-shuffled": "oracle", "espnetv2-random": "espnetv2"}
#: The contrasts claimed, stated before the runs: (condition, reference, label).
CONTRASTS = (
    ("occluded", "clean", "occlusion's cost: occluded − as they are"),
    ("oracle", "occluded", "pasted pixels' mask − none"),
    ("espnetv2", "occluded", "ESPNetv2's mask − none"),
    ("espnetv2-objects", "occluded", "ESPNetv2's objects only − none"),
    ("oracle", "oracle-random", "pasted pixels' mask − random cells"),
    ("oracle", "oracle-shuffled", "pasted pixels' mask − another image's"),
    ("espnetv2", "espnetv2-random", "ESPNetv2's mask − random cells"),
)
FIELDS = (
    "pair",
    "model",
    "mask",
    "reference",
    "R@1",
    "R@5",
    "R@10",
    "gain",
    "ci_low",
    "ci_high",
    "excludes_0",
    "level",
)
_DRAW = re.compile(r" seed (\d+)$")


def condition_hits(folder: Path, condition: str) -> dict[tuple[str, int], dict]:
    """One condition's jobs in one pair's folder by (aggregator, occluder draw; 0 for the frames as they are):
    their eval.json and hits, checked against the jobs run.sh gives it."""
    sweep, recorded, _ = CONDITIONS[condition]
    jobs = {}
    for evaluation in read_evaluations(folder / sweep):
        result = evaluation.result
        if any(result.get(k) != v for k, v in recorded.items()):
            continue
        drawn = _DRAW.search(result["set"])
        jobs[(result["aggregator"], int(drawn.group(1)) if drawn else 0)] = {"result": result, "hits": evaluation.hits}
    wanted = {(a, d) for a in MODELS for d in ((0,) if condition == "clean" else DRAWS)}
    if set(jobs) != wanted:
        raise SemvprError(f"{folder / sweep}: {condition} jobs {sorted(jobs)}, expected {sorted(wanted)}; rerun run.sh")
    return jobs


@exit_on_user_error
def main() -> None:
    out = summary_input(__doc__.splitlines()[0], "experiments/occluded-real-coverage/run.sh")
    pairs = [pair for pair in PAIRS if (out / pair).is_dir()]  # those run.sh ran (PAIRS), in this order
    if not pairs:
        raise SemvprError(f"{out} holds none of the pairs {', '.join(PAIRS)}; run run.sh first")
    rows: list[dict[str, object]] = []
    saved: dict[str, np.ndarray] = {}
    # (pair, aggregator, condition) → each query's R@1 per draw (draws × queries; the frames as they are: 1 row)
    r1: dict[tuple[str, str, str], np.ndarray] = {}
    for pair in pairs:
        jobs = {condition: condition_hits(out / pair, condition) for condition in CONDITIONS}
        for aggregator, model in MODELS.items():
            for condition, (_, _, label) in CONDITIONS.items():
                draws = sorted(d for a, d in jobs[condition] if a == aggregator)
                drawn = [jobs[condition][(aggregator, d)] for d in draws]
                for draw, job in zip(draws, drawn, strict=True):
                    saved[f"{pair}|{aggregator}|{condition}|{draw}"] = job["hits"]
                r1[(pair, aggregator, condition)] = np.stack([job["hits"][:, 0] for job in drawn]).astype(float)
                recalls = {
                    f"R@{n}": round(float(np.mean([j["result"][f"test/R@{n}"] for j in drawn])), 2) for n in (1, 5, 10)
                }
                row = {"pair": pair.replace("-", " → "), "model": model, "mask": label, **recalls}
                reference = REFERENCE.get(condition, "occluded" if condition != "clean" else None)
                if reference is not None:
                    hits, base = (r1[(pair, aggregator, c)] for c in (condition, reference))
                    # Paired on the same draw (the frames as they are: one evaluation for every draw).
                    row |= {"reference": CONDITIONS[reference][2]}
                    row |= paired_gain(hits.mean(0), np.broadcast_to(base, hits.shape).mean(0)).record(LEVEL)
                rows.append(row)
    level = round(corrected_level(len(CONTRASTS)), 4)
    for condition, reference, label in CONTRASTS:
        keys = [(p, a) for p in pairs for a in MODELS]
        comparisons = [(r1[(*k, condition)].mean(0), r1[(*k, reference)].mean(0)) for k in keys]
        rows.append(
            {"pair": "all three", "model": "both", "mask": label} | pooled_gain(comparisons, level=level).record(level)
        )
    write_summary(Path(__file__).parent, FIELDS, rows, saved)
    write_json(Path(__file__).parent / "coverage.json", coverage(out / "cache"))
    print(f"wrote {Path(__file__).parent / 'coverage.json'}")


def coverage(cache: Path) -> dict[str, object]:
    """What the draws covered: CamVid train's shares they were drawn from (``occluders.json``'s record, one for
    every draw), and the fraction of each composite's pixels pasted (mean, 90th percentile, max over the
    composites of every draw)."""
    shares, pasted = None, []
    for record_file in sorted(cache.glob("occluded-*/occluders.json")):
        record = read_json(record_file, "occluders record")
        if not isinstance(record, dict) or record.get("coverage") != "camvid":
            continue
        if shares is not None and record.get("camvid_train_shares") != shares:
            raise SemvprError(f"{record_file}: CamVid train's shares differ from the other draws'")
        shares = record.get("camvid_train_shares")
        pasted += [float(image["coverage"]) for image in record["images"].values()]
    if shares is None or not pasted:
        raise SemvprError(f"no draws at CamVid train's coverage under {cache}; run run.sh first")
    values = np.asarray(pasted)
    return {
        "camvid_train_shares": shares,
        "pasted": {"composites": len(values), "mean": float(values.mean()), "p90": float(np.percentile(values, 90))}
        | {"max": float(values.max())},
    }


if __name__ == "__main__":
    main()

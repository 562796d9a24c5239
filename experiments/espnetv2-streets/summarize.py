"""results.csv of the espnetv2-streets sweeps (run.sh OUT): per pair and model, Recall@1/5/10 with no mask and
with ESPNetv2's, the mask's R@1 gain paired by query with its 95 % bootstrap interval, and one pooled gain over
every pair and model, the places resampled jointly (frame i is the same place in every traversal, so one
resample of the 200 places draws the same places for all six comparisons).

    python experiments/espnetv2-streets/summarize.py OUT
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.reporting.paired import LEVEL, RESAMPLES, paired_gain

PAIRS = ("day_left-night_right", "day_right-night_right", "day_left-day_right")
MODELS = {"gem": "no VPR training: GeM (p = 3)", "netvlad": "no VPR training: NetVLAD (k-means on SynthCity)"}
MASKS = {"none": "none", "teacher": "ESPNetv2 (Cityscapes, s=2.0)"}
FIELDS = ("pair", "model", "mask", "R@1", "R@5", "R@10", "gain", "ci_low", "ci_high", "excludes_0", "precision")


def sweep_jobs(folder: Path) -> dict[tuple[str, str], tuple[dict, np.ndarray]]:
    """Each job of one pair's sweep by (aggregator, mask): its eval.json and its first-hit ranks."""
    jobs = {}
    for record in sorted(folder.glob("*/eval.json")):
        result = json.loads(record.read_text())
        if result.get("status") != "ok":
            raise SemvprError(f"{record}: status {result.get('status')!r}; rerun run.sh")
        ranks = np.load(record.parent / "ranks.npy", allow_pickle=False)
        if abs(100.0 * np.mean(ranks == 0) - result["test/R@1"]) > 0.006:
            raise SemvprError(f"{record.parent}: ranks.npy does not give eval.json's R@1")
        jobs[(result["aggregator"], result["mask"])] = (result, ranks)
    wanted = {(a, m) for a in MODELS for m in MASKS}
    if set(jobs) != wanted:
        raise SemvprError(f"{folder}: jobs {sorted(jobs)}, expected {sorted(wanted)}; rerun run.sh")
    return jobs


def pooled(differences: list[np.ndarray], seed: int = 0) -> tuple[float, float, float]:
    """The mean of several per-place differences (same places, same order) and its percentile-bootstrap interval,
    the places resampled jointly."""
    stacked = np.stack(differences)
    draws = np.random.default_rng(seed).integers(0, stacked.shape[1], (RESAMPLES, stacked.shape[1]))
    means = stacked[:, draws].mean(axis=(0, 2))
    tail = 100.0 * (1 - LEVEL) / 2
    low, high = np.percentile(means, [tail, 100.0 - tail])
    return float(stacked.mean()), float(low), float(high)


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="the folder run.sh wrote")
    out = ap.parse_args().out
    if not out.is_dir():
        raise SemvprError(f"{out} is not a folder run.sh wrote (bash experiments/espnetv2-streets/run.sh OUT)")
    rows, differences = [], []
    for pair in PAIRS:
        jobs = sweep_jobs(out / pair)
        for aggregator, model in MODELS.items():
            base = jobs[(aggregator, "none")][1] == 0
            for mask, label in MASKS.items():
                result, ranks = jobs[(aggregator, mask)]
                row = {"pair": pair.replace("-", " → "), "model": model, "mask": label}
                row |= {f"R@{n}": result[f"test/R@{n}"] for n in (1, 5, 10)}
                row["precision"] = result.get("precision", "")
                if mask != "none":
                    gain = paired_gain(ranks == 0, base)
                    row |= {"gain": round(gain.gain, 2), "ci_low": round(gain.low, 2), "ci_high": round(gain.high, 2)}
                    row["excludes_0"] = "yes" if gain.significant else "no"
                    differences.append(100.0 * ((ranks == 0).astype(float) - base))
                rows.append(row)
    mean, low, high = pooled(differences)
    rows.append(
        {"pair": "all three", "model": "both", "mask": MASKS["teacher"], "gain": round(mean, 2)}
        | {"ci_low": round(low, 2), "ci_high": round(high, 2), "excludes_0": "yes" if low > 0 or high < 0 else "no"}
    )
    target = Path(__file__).parent / "results.csv"
    with target.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {target}")


if __name__ == "__main__":
    main()

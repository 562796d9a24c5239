"""The real-streets tables: every evaluation under OUT/eval (run.sh), by pair, model and mask source.

    python experiments/real-streets/summarize.py OUT [--out experiments/real-streets/results.md]

Per pair, one row per model and mask source: Recall@1/5/10 (mean ± sample std over the seeds of a
trained model; one number for an untrained baseline) and the R@1 gain of the mask over the same
model without one, paired by query: each query's hit rate averaged over the seeds, the difference
resampled over the queries (``semvpr.reporting.paired``, 10,000 percentile-bootstrap resamples, 95 %).
A gain whose interval excludes 0 is marked with *.
"""

from __future__ import annotations

import argparse
import re
from collections import defaultdict
from pathlib import Path

import numpy as np

from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import read_json, write_text
from semvpr.reporting.paired import paired_gain

#: Evaluation sweeps by mask source: run.sh's directory names and the table's words.
MASKS = {
    "none": "none",
    "own": "own SynthCity mask",
    "camvid-student": "CamVid student",
    "camvid-teacher": "CamVid teacher",
}
#: recipe=gsv aggregators of run.sh's second training sweep, and the masks their checkpoints trained with.
GSV_AGGREGATORS = ("gem", "mixvpr", "salad", "boq")
GSV_TRAINED_WITH = {
    "none": "without a mask",
    "student": "with the SynthCity student",
    "teacher": "with the SynthCity teacher",
}
#: Models in table order: the filter of a SynthCity checkpoint, a recipe=gsv aggregator and the mask it
#: trained with, or an untrained aggregator.
MODELS = {
    "untrained gem": "no VPR training: GeM (p = 3)",
    "untrained netvlad": "no VPR training: NetVLAD (k-means on SynthCity)",
    "none": "`filter=none` (NetVLAD)",
    "attention": "`filter=attention` (SRAL)",
    "unet": "`filter=unet` (SRAL + SynthCity student)",
    "mask2former": "`filter=mask2former` (SRAL + SynthCity teacher)",
    "learned unet": "`filter=unet` with learned class weights (SRAL + SynthCity student)",
    "learned mask2former": "`filter=mask2former` with learned class weights (SRAL + SynthCity teacher)",
    **{
        f"gsv {a} {m}": f"`{a}` (recipe=gsv, trained {words})"
        for a in GSV_AGGREGATORS
        for m, words in GSV_TRAINED_WITH.items()
    },
}
PAIRS = {
    "day_left-night_right": "day_left → night_right (day/night)",
    "day_right-night_right": "day_right → night_right (day/night, same side)",
    "day_left-day_right": "day_left → day_right (lateral viewpoint)",
}


def _model(result: dict) -> tuple[str, int]:
    """(model key, seed) of an evaluation: a checkpoint of a training sweep, or an untrained baseline."""
    if result["checkpoint"] == "none":
        return f"untrained {result['aggregator']}", 0
    found = re.search(r"filter\.weights=learned,filter=(\w+),seed=(\d+)", result["checkpoint"])
    if found:
        return f"learned {found.group(1)}", int(found.group(2))
    found = re.search(r"filter=(\w+),seed=(\d+)", result["checkpoint"])
    if found:
        return found.group(1), int(found.group(2))
    found = re.search(r"aggregator=(\w+),mask=(\w+),recipe=gsv,seed=(\d+)", result["checkpoint"])
    if found:
        return f"gsv {found.group(1)} {found.group(2)}", int(found.group(3))
    raise SystemExit(f"{result['checkpoint']}: not a checkpoint of run.sh's training sweeps")


def collect(out: Path) -> dict[str, dict[tuple[str, str], dict[int, tuple[dict, np.ndarray]]]]:
    """{pair: {(model, mask source): {seed: (eval.json, ranks)}}} of every ok evaluation under OUT/eval."""
    runs: dict = defaultdict(lambda: defaultdict(dict))
    for found in sorted((out / "eval").glob("*/*/*/eval.json")):
        job, sweep, pair = found.parent, found.parent.parent.name, found.parent.parent.parent.name
        result = read_json(found, "eval result")
        if result.get("status") != "ok":
            raise SystemExit(f"{job}: {result.get('error')}")
        model, seed = _model(result)
        # run.sh names a sweep <checkpoints>-<mask source> (or just the source): the source is its ending.
        source = next((m for m in MASKS if sweep == m or sweep.endswith(f"-{m}")), None)
        if source is None:
            raise SystemExit(f"{found.parent.parent}: not a mask source of run.sh ({', '.join(MASKS)})")
        runs[pair][(model, source)][seed] = (result, np.load(job / "ranks.npy", allow_pickle=False))
    return runs


def _recall(runs: dict[int, tuple[dict, np.ndarray]], n: int) -> str:
    values = [100.0 * float(np.mean((r >= 0) & (r < n))) for _, r in runs.values()]
    return f"{values[0]:.1f}" if len(values) == 1 else f"{np.mean(values):.1f} ± {np.std(values, ddof=1):.1f}"


def _hit_rate(runs: dict[int, tuple[dict, np.ndarray]]) -> np.ndarray:
    """Each query's R@1 hit rate over the seeds."""
    return np.mean([r == 0 for _, r in runs.values()], axis=0)


def table(pair: str, cells: dict[tuple[str, str], dict[int, tuple[dict, np.ndarray]]]) -> list[str]:
    """The markdown table of one pair."""
    any_run = next(iter(next(iter(cells.values())).values()))[0]
    lines = [
        f"### {PAIRS.get(pair, pair)}",
        "",
        f"`{any_run['set']}`: {any_run['database']} database images, {any_run['queries']} queries.",
        "",
        "| model | mask | seeds | R@1 | R@5 | R@10 | R@1 gain over no mask [95 % CI] |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    for model, label in MODELS.items():
        base = cells.get((model, "none"))
        for source, words in MASKS.items():
            runs = cells.get((model, source))
            if runs is None:
                continue
            gain = ""
            if source != "none" and base is not None and sorted(base) == sorted(runs):
                paired = paired_gain(_hit_rate(runs), _hit_rate(base))
                gain = paired.text() + (" *" if paired.significant else "")
            recalls = " | ".join(_recall(runs, n) for n in (1, 5, 10))
            lines.append(f"| {label} | {words} | {len(runs)} | {recalls} | {gain} |")
    return lines


@exit_on_user_error
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the OUT directory of run.sh")
    parser.add_argument("--out", dest="md", type=Path, default=Path(__file__).with_name("results.md"))
    args = parser.parse_args()
    runs = collect(args.out)
    if not runs:
        raise SystemExit(f"no evaluations under {args.out / 'eval'}; run run.sh first")
    lines = [
        "# Real streets: Gardens Point Walking",
        "",
        "Recall@N in % (mean ± sample std over seeds); the gain is paired by query over the seeds' mean hit "
        "rate, 95 % percentile bootstrap over the queries (10,000 resamples); * marks an interval that "
        "excludes 0. Written by `summarize.py` from the evaluations of `run.sh`.",
        "",
    ]
    for pair in sorted(runs, key=lambda p: list(PAIRS).index(p) if p in PAIRS else len(PAIRS)):
        lines += [*table(pair, runs[pair]), ""]
    write_text(args.md, "\n".join(lines))
    print(args.md)


if __name__ == "__main__":
    main()

"""The occluded-streets tables, data file and figure: every evaluation under OUT/eval (run.sh).

    python experiments/occluded-streets/summarize.py OUT [--out-dir experiments/occluded-streets] [--logs LOG ...]

Writes ``results.csv`` (one row per pair, model, condition, mask and coverage), ``results.md`` and
``figure_coverage.png`` (R@1 against coverage, one panel per pair, one line per mask); with ``--logs``
(run.sh's stderr), ``timings.csv``: the seconds of each compositing and each trunk pass its stage lines
report.

Conditions: ``clean`` (the frames as they are: coverage 0), ``occluded`` (CamVid test objects pasted over
the coverage's share of every image) and ``holes`` (the same draws' oracle masks on the frames without the
objects: what the holes alone cost). A model is an untrained aggregator or the checkpoints of one setting of a
training sweep (its run folders' names without ``seed=N`` and ``threads=N``); a cell's runs are its models'
training seeds × the occluder seeds. Recall is the mean ± sample std over the runs. Each query's R@1 hit rate
is averaged over the runs before pairing (``semvpr.reporting.paired``: 10,000 percentile-bootstrap resamples
over the queries, 95 %):

- gain: a mask's R@1 over no mask on the same images (``holes``: over no mask on the clean frames);
- recovered: the share of the objects' damage the mask undoes, (masked − occluded) / (clean − occluded),
  where the damage's own interval excludes 0;
- leak (the oracle only): occluded with the oracle against the holes with the oracle: what the pasted
  objects still cost once every pasted pixel is masked (through the trunk's receptive field).
"""

from __future__ import annotations

import argparse
import csv
import io
import re
from collections import defaultdict
from pathlib import Path

import numpy as np

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import atomic_file, read_json, write_csv, write_text
from semvpr.reporting.paired import PairedGain, RecoveredShare, paired_gain, recovered_share

#: run.sh's sweep names: m<model index>-<condition>-<mask>.
SWEEP = re.compile(r"m(\d+)-(clean|occluded|holes)-(\w+)")
#: What the occluders add to a set's name (semvpr.data.occluders.occlude).
OCCLUDED_NAME = re.compile(r"\+ CamVid (\d+)% seed (\d+)( \(holes only\))?$")
MASK_ORDER = ("none", "oracle", "student", "teacher")
MASK_WORDS = {
    "none": "none",
    "oracle": "oracle (the pasted pixels)",
    "student": "CamVid student",
    "teacher": "CamVid teacher",
}
MODEL_WORDS = {
    "untrained netvlad": "NetVLAD (k-means, no VPR training)",
    "untrained gem": "GeM (p = 3, no training)",
    # real-streets' training sweeps (the four-way comparison; recipe=gsv without a mask), by run folder.
    "filter=none": "NetVLAD, SynthCity (filter=none)",
    "filter=attention": "SRAL, SynthCity (filter=attention)",
    "filter=unet": "SRAL, SynthCity, trained with its student's mask (filter=unet)",
    "filter=mask2former": "SRAL, SynthCity, trained with its teacher's mask (filter=mask2former)",
    "aggregator=mixvpr,mask=none,recipe=gsv": "MixVPR, SynthCity (recipe=gsv)",
    "aggregator=salad,mask=none,recipe=gsv": "SALAD, SynthCity (recipe=gsv)",
}
PAIRS = {
    "day_left-night_right": "day_left → night_right (day/night)",
    "day_right-night_right": "day_right → night_right (day/night, same side)",
    "day_left-day_right": "day_left → day_right (lateral viewpoint)",
}
FIELDS = (
    "pair",
    "model",
    "condition",
    "mask",
    "coverage",
    "models",
    "runs",
    "queries",
    "r1",
    "r1_std",
    "r5",
    "r5_std",
    "gain",
    "gain_low",
    "gain_high",
    "recovered",
    "recovered_low",
    "recovered_high",
    "leak",
    "leak_low",
    "leak_high",
)

#: Stage lines of a finished compositing and of a finished trunk pass (semvpr.core.logs.Progress).
COMPOSITE_LINE = re.compile(r"semvpr: (.+?): CamVid objects \(.*\): (\d+)/\d+ images in ([\d.]+) (s|min|h)$")
TRUNK_LINE = re.compile(r"semvpr: (gardens_point .+?) (db|q): (\d+)/\d+ images in ([\d.]+) (s|min|h)$")
SECONDS = {"s": 1.0, "min": 60.0, "h": 3600.0}

#: A Hydra sweep's training seed in a run folder's name (``filter=unet,seed=2``), and the overrides there that
#: do not make another model.
TRAIN_SEED = re.compile(r"seed=(\d+)")
NOT_MODEL = re.compile(r"(seed|threads)=.*")
#: {(training seed, occluder seed): each query's first-hit rank}: the runs of one cell.
Seeds = dict[tuple[int, int], np.ndarray]
#: {pair: {(model, condition, mask, coverage): runs}}
Runs = dict[str, dict[tuple[str, str, str, int], Seeds]]


def _model(result: dict) -> tuple[str, int]:
    """(model, training seed): an untrained aggregator (seed 0), or the checkpoint's run folder
    (…/<run>/checkpoints/x.ckpt) without its ``seed=N`` and ``threads=N`` (a sweep's runs of one setting are one
    model)."""
    if not isinstance(result.get("checkpoint"), str) or not isinstance(result.get("aggregator"), str):
        raise SemvprError("an eval.json without its checkpoint and aggregator; rerun run.sh")
    if result["checkpoint"] == "none":
        return f"untrained {result['aggregator']}", 0
    path = Path(result["checkpoint"])
    run = path.parent.parent.name if path.parent.name == "checkpoints" else path.name
    parts = run.split(",")
    seeds = [int(found.group(1)) for part in parts if (found := TRAIN_SEED.fullmatch(part))]
    rest = ",".join(part for part in parts if not NOT_MODEL.fullmatch(part))
    return rest or run, seeds[0] if seeds else 0


def _ranks(job: Path, result: dict) -> np.ndarray:
    """The job's first-hit ranks (``ranks.npy``: whole numbers, one per query), checked against its eval.json's
    R@1 and R@5."""
    try:
        ranks = np.load(job / "ranks.npy", allow_pickle=False)
    except (OSError, ValueError) as err:
        raise SemvprError(f"{job / 'ranks.npy'} is not readable ranks ({type(err).__name__})") from None
    if ranks.ndim != 1 or ranks.dtype.kind not in "iu" or len(ranks) != result.get("queries"):
        raise SemvprError(f"{job / 'ranks.npy'}: not {result.get('queries')} whole-number ranks ({ranks.dtype})")
    for n in (1, 5):
        if abs(100.0 * float(np.mean((ranks >= 0) & (ranks < n))) - result.get(f"test/R@{n}", np.nan)) > 0.006:
            raise SemvprError(f"{job}: ranks.npy does not give eval.json's R@{n}; rerun its sweep")
    return ranks


def collect(out: Path) -> Runs:
    """Every ok evaluation under OUT/eval, by pair and cell, with its per-query ranks; every occluded cell of a
    pair must hold the same occluder draws (a stopped sweep left fewer)."""
    runs: Runs = defaultdict(lambda: defaultdict(dict))
    for found in sorted((out / "eval").glob("*/*/*/eval.json")):
        job, sweep, pair = found.parent, found.parent.parent.name, found.parent.parent.parent.name
        named = SWEEP.fullmatch(sweep)
        if named is None:
            raise SemvprError(f"{found.parent.parent}: not a sweep of run.sh (m<i>-<condition>-<mask>)")
        result = read_json(found, "eval result")
        if not isinstance(result, dict) or result.get("status") != "ok":
            raise SemvprError(f"{job}: not a finished evaluation; rerun run.sh")
        condition, mask = named.group(2), named.group(3)
        occluded = OCCLUDED_NAME.search(str(result.get("set")))
        if (occluded is None) != (condition == "clean"):
            raise SemvprError(f"{job}: set {result.get('set')!r} does not match its sweep {sweep}")
        coverage, seed = (int(occluded.group(1)), int(occluded.group(2))) if occluded else (0, 0)
        model, train_seed = _model(result)
        runs[pair][(model, condition, mask, coverage)][(train_seed, seed)] = _ranks(job, result)
    for pair, cells in runs.items():
        draws = {k: {d for _, d in seeds} for k, seeds in cells.items() if k[1] != "clean"}
        every = set().union(*draws.values()) if draws else set()
        for key, held in draws.items():
            if held != every:
                raise SemvprError(
                    f"{out / 'eval' / pair}: {' '.join(map(str, key))} holds occluder seeds {sorted(held)}, the pair's "
                    f"other cells {sorted(every)}; rerun run.sh (a stopped sweep left it short)"
                )
    return runs


def _hits(seeds: Seeds) -> np.ndarray:
    """Each query's R@1 hit rate over the runs."""
    return np.mean([r == 0 for r in seeds.values()], axis=0)


def _recall(seeds: Seeds, n: int) -> tuple[float, float]:
    values = [100.0 * float(np.mean((r >= 0) & (r < n))) for r in seeds.values()]
    return float(np.mean(values)), float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


def _model_order(model: str) -> tuple[int, str]:
    """Models in MODEL_WORDS' order, any other after them by name."""
    return (list(MODEL_WORDS).index(model) if model in MODEL_WORDS else len(MODEL_WORDS), model)


def _pair_order(pair: str) -> int:
    """Pairs in PAIRS' order, any other after them."""
    return list(PAIRS).index(pair) if pair in PAIRS else len(PAIRS)


def _pairs_with(base: Seeds, seeds: Seeds) -> bool:
    """Whether ``base`` holds the same runs as ``seeds`` (the same models on the same draws), or the clean
    frames' one run of each of the same models."""
    return sorted(base) in (sorted(seeds), sorted({(train, 0) for train, _ in seeds}))


def rows(pair: str, cells: dict[tuple[str, str, str, int], Seeds]) -> list[dict[str, object]]:
    """One row per cell of a pair, with its gains (see the module's docstring)."""
    out = []
    order = {m: i for i, m in enumerate(MASK_ORDER)}
    conditions = {"clean": 0, "occluded": 1, "holes": 2}
    for key in sorted(cells, key=lambda k: (*_model_order(k[0]), conditions[k[1]], k[3], order.get(k[2], 9), k[2])):
        model, condition, mask, coverage = key
        seeds = cells[key]
        r1, r1_std = _recall(seeds, 1)
        r5, r5_std = _recall(seeds, 5)
        row: dict[str, object] = {
            "pair": pair,
            "model": model,
            "condition": condition,
            "mask": mask,
            "coverage": coverage,
            "models": len({train for train, _ in seeds}),
            "runs": len(seeds),
            "queries": len(next(iter(seeds.values()))),
            "r1": round(r1, 2),
            "r1_std": round(r1_std, 2),
            "r5": round(r5, 2),
            "r5_std": round(r5_std, 2),
        }
        clean = cells.get((model, "clean", "none", 0))
        base = clean if condition == "holes" else cells.get((model, condition, "none", coverage))
        if mask != "none" and base is not None and _pairs_with(base, seeds):
            gain = paired_gain(_hits(seeds), _hits(base))
            row |= {"gain": round(gain.gain, 2), "gain_low": round(gain.low, 2), "gain_high": round(gain.high, 2)}
            if condition == "occluded" and clean is not None:
                share = recovered_share(_hits(seeds), _hits(base), _hits(clean))
                if share is not None:
                    row |= {
                        "recovered": round(share.share, 3),
                        "recovered_low": round(share.low, 3),
                        "recovered_high": round(share.high, 3),
                    }
        holes = cells.get((model, "holes", mask, coverage))
        if condition == "occluded" and holes is not None and sorted(holes) == sorted(seeds):
            leak = paired_gain(_hits(seeds), _hits(holes))
            row |= {"leak": round(leak.gain, 2), "leak_low": round(leak.low, 2), "leak_high": round(leak.high, 2)}
        out.append(row)
    return out


def _interval(row: dict[str, object], name: str) -> str:
    """A gain (points) or a recovered share of a row with its interval, * where the interval excludes 0."""
    if name not in row:
        return ""
    value, low, high = (float(row[k]) for k in (name, f"{name}_low", f"{name}_high"))
    kind = RecoveredShare if name == "recovered" else PairedGain
    return kind(value, low, high, 0).text() + (" *" if low > 0 or high < 0 else "")


def table(pair: str, pair_rows: list[dict[str, object]]) -> list[str]:
    """The markdown table of one pair."""
    lines = [
        f"### {PAIRS.get(pair, pair)}",
        "",
        "| model | images | coverage | mask | runs | R@1 | R@5 | R@1 gain over no mask [95 % CI] "
        "| damage recovered [95 % CI] | leak: oracle vs holes [95 % CI] |",
        "|---|---|---:|---|---:|---:|---:|---|---|---|",
    ]
    for row in pair_rows:
        std = row["runs"] != 1
        r1 = f"{row['r1']:.1f}" + (f" ± {row['r1_std']:.1f}" if std else "")
        r5 = f"{row['r5']:.1f}" + (f" ± {row['r5_std']:.1f}" if std else "")
        mask = MASK_WORDS.get(str(row["mask"]), row["mask"])
        model = MODEL_WORDS.get(str(row["model"]), row["model"])
        gains = " | ".join(_interval(row, name) for name in ("gain", "recovered", "leak"))
        cells = [model, row["condition"], f"{row['coverage']} %", mask, row["runs"], r1, r5]
        lines.append(f"| {' | '.join(str(c) for c in cells)} | {gains} |")
    return lines


def summary(all_rows: list[dict[str, object]]) -> list[str]:
    """One line per pair, model and coverage: R@1 clean, occluded without a mask, and with each mask (the share
    of the damage it recovers beside it, where given)."""
    masks = [m for m in MASK_ORDER[1:] if any(r["mask"] == m for r in all_rows)]
    lines = [
        "| pair | model | coverage | clean | no mask | " + " | ".join(MASK_WORDS[m] for m in masks) + " |",
        "|---|---|---:|---:|---:|" + "---:|" * len(masks),
    ]
    cells = {(r["pair"], r["model"], r["condition"], r["mask"], r["coverage"]): r for r in all_rows}
    keys = sorted(
        {(r["pair"], r["model"], r["coverage"]) for r in all_rows if r["condition"] == "occluded"},
        key=lambda k: (_pair_order(str(k[0])), *_model_order(str(k[1])), k[2]),
    )
    for pair, model, coverage in keys:
        clean = cells.get((pair, model, "clean", "none", 0))
        values = [f"{clean['r1']:.1f}" if clean else "–"]
        for mask in ("none", *masks):
            row = cells.get((pair, model, "occluded", mask, coverage))
            text = "–" if row is None else f"{row['r1']:.1f}"
            if row is not None and "recovered" in row:
                text += f" ({int(round(100 * float(row['recovered'])))} %)".replace("-", "−")
            values.append(text)
        words = MODEL_WORDS.get(str(model), model)
        named = PAIRS.get(str(pair), str(pair)).split(" (")[0]
        lines.append(f"| {named} | {words} | {coverage} % | " + " | ".join(values) + " |")
    return lines


def figure(all_rows: list[dict[str, object]], out: Path) -> None:
    """R@1 against coverage, one panel per pair, one line per mask (model: the untrained NetVLAD where run)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pairs = [p for p in PAIRS if any(r["pair"] == p for r in all_rows)]
    models = sorted({str(r["model"]) for r in all_rows})
    model = "untrained netvlad" if "untrained netvlad" in models else models[0]
    fig, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 3.4), squeeze=False)
    for ax, pair in zip(axes[0], pairs):
        mine = [r for r in all_rows if r["pair"] == pair and r["model"] == model]
        clean = {r["mask"]: r for r in mine if r["condition"] == "clean"}
        for mask in MASK_ORDER:
            for condition, style in (("occluded", "-o"), ("holes", ":s")):
                points = sorted(
                    (r["coverage"], r["r1"], r["r1_std"])
                    for r in mine
                    if (r["condition"], r["mask"]) == (condition, mask)
                )
                if not points:
                    continue
                start = clean.get(mask) or clean.get("none")
                if start is not None:
                    points = [(0, start["r1"], 0.0), *points]
                x, y, e = (np.array(v, dtype=float) for v in zip(*points))
                label = MASK_WORDS[mask] + (" on the frames without objects (holes)" if condition == "holes" else "")
                ax.errorbar(x, y, yerr=e, fmt=style, capsize=2, label=label)
        ax.set_title(PAIRS[pair], fontsize=9)
        ax.set_xlabel("pixels covered by pasted objects (%)")
        ax.set_ylabel("R@1 (%)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"Gardens Point Walking with CamVid objects pasted in: {MODEL_WORDS.get(model, model)}", fontsize=10)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    with atomic_file(out) as fh:
        fh.write(buffer.getvalue())


def timings(logs: list[Path]) -> str:
    """``timings.csv``: kind (composite | trunk), set, images, seconds, from the logs' stage lines."""
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(["kind", "set", "images", "seconds"])
    for log in logs:
        for line in log.read_text(encoding="utf-8", errors="replace").splitlines():
            if found := COMPOSITE_LINE.search(line):
                name, images, value, unit = found.groups()
                writer.writerow(["composite", name, images, float(value) * SECONDS[unit]])
            elif found := TRUNK_LINE.search(line):
                name, side, images, value, unit = found.groups()
                writer.writerow(["trunk", f"{name} {side}", images, float(value) * SECONDS[unit]])
    return text.getvalue()


@exit_on_user_error
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the OUT directory of run.sh")
    parser.add_argument("--out-dir", type=Path, default=Path(__file__).parent)
    parser.add_argument("--logs", type=Path, nargs="*", default=[], help="run.sh's stderr, for timings.csv")
    parser.add_argument("--machine", default=None, help="where the evaluations ran, for results.md")
    args = parser.parse_args()
    runs = collect(args.out)
    if not runs:
        raise SemvprError(f"no evaluations under {args.out / 'eval'}; run run.sh first")
    pairs = sorted(runs, key=_pair_order)
    by_pair = {pair: rows(pair, runs[pair]) for pair in pairs}
    all_rows = [r for pair in pairs for r in by_pair[pair]]
    write_csv(args.out_dir / "results.csv", FIELDS, all_rows)
    lines = [
        "# Occluded streets: Gardens Point Walking with CamVid objects pasted in",
        "",
        "Recall@N in % (mean ± sample std over the runs: a model's training seeds × the occluder seeds); gains "
        "paired by query over the runs' mean hit rate, 95 % percentile bootstrap over the queries (10,000 "
        "resamples); * marks an interval that excludes 0. Damage recovered: (masked − occluded) / (clean − "
        "occluded), where the damage's interval excludes 0. Leak: the oracle on the occluded images against the "
        "oracle on the frames without objects. "
        "Written by `summarize.py` from the evaluations of `run.sh` (numbers: `results.csv`).",
        "",
        "Command: `bash experiments/occluded-streets/run.sh OUT ../shared/realdata/gardens_point "
        "../shared/realdata/camvid`, then `python experiments/occluded-streets/summarize.py OUT`."
        + (f" Machine: {args.machine}." if args.machine else ""),
        "",
        "## R@1 at a glance",
        "",
        "R@1 in %: on the frames as they are (clean), with the objects pasted in and no mask, and with each mask "
        "(in brackets the share of the objects' damage it recovers, where the damage's interval excludes 0). "
        "Every interval: the tables per pair below.",
        "",
        *summary(all_rows),
        "",
        "## Per pair",
        "",
    ]
    for pair in pairs:
        lines += [*table(pair, by_pair[pair]), ""]
    write_text(args.out_dir / "results.md", "\n".join(lines))
    figure(all_rows, args.out_dir / "figure_coverage.png")
    if args.logs:
        write_text(args.out_dir / "timings.csv", timings(args.logs))
    print(args.out_dir / "results.md")


if __name__ == "__main__":
    main()

"""A training sweep's report: results.csv, results.md and the figures, from the sweep directory as
``semvpr.reporting.sweep`` reads it back (one row per backbone · aggregator · mask, the paired R@1
gains, the aggregator × mask matrix, the learned class weights, the failed jobs)."""

from __future__ import annotations

import csv
import io
import math
import os
import shutil
from pathlib import Path
from typing import Any

from semvpr.core.io import check_replaceable, temp_dir, write_text
from semvpr.reporting.markdown import md_cell, terminal_text
from semvpr.reporting.sweep import LEARNED, NO_MASK, Sweep, cell_name, load_sweep, mean_std, numeric_weights
from semvpr.retrieval.recall import RECALL_NS


def _rows(sweep: Sweep) -> list[dict[str, Any]]:
    """One aggregated row per (backbone, aggregator, mask), backbones outer, rows in reading order."""
    rows = []
    for bb in sweep.backbones:
        for cell in sweep.cells:
            jobs = sweep.jobs_of(cell, bb)
            if not jobs:
                continue
            ok = [j for j in jobs if j.ok]
            row: dict[str, Any] = {
                "cell": cell,
                "aggregator": jobs[0].aggregator,
                "mask": jobs[0].mask,
                "backbone": bb,
                "n": len(ok),
                "failed": len(jobs) - len(ok),
                "seeds": sorted(j.seed for j in ok if j.seed is not None),
            }
            for n in RECALL_NS:
                row[f"R@{n}"] = mean_std([j.recall(n) for j in ok])
            walls = [
                float(j.metrics["wall_time_s"]) for j in ok if isinstance(j.metrics.get("wall_time_s"), (int, float))
            ]
            row["wall_time_s"] = mean_std(walls)[0]
            # The epoch each seed's tested weights come from (best val/R@5), in the order of "seeds".
            seeded = sorted((j for j in ok if j.seed is not None), key=lambda j: j.seed)
            row["best_epochs"] = [j.metrics.get("best/epoch") for j in seeded]
            rows.append(row)
    return rows


def _fmt(x: float, signed: bool = False) -> str:
    """One decimal; a typographic minus so signed gains read as −2.0 / +3.1."""
    if not math.isfinite(x):
        return "–"
    return (f"{x:+.1f}" if signed else f"{x:.1f}").replace("-", "−")


def _epochs(epochs: list[Any], sep: str) -> str:
    """Best epochs as recorded; ? for a job from before metrics.json kept its epoch."""
    return sep.join(str(e) if isinstance(e, int) else "?" for e in epochs)


def _csv_text(rows: list[dict[str, Any]], partial: bool = False) -> str:
    """Machine-readable table: means and stds unrounded-enough (4 decimals), blanks for missing; each row says
    whether a job of the sweep had not finished (``partial``: still running, stopped, or never started, so its
    row may lack jobs)."""
    buf = io.StringIO()
    cols = (
        ["aggregator", "mask", "backbone", "n", "seeds"]
        + [f"R@{n}_{s}" for n in RECALL_NS for s in ("mean", "std")]
        + ["wall_time_s", "failed", "best_epochs", "partial"]
    )
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(cols)
    num = lambda x: "" if not math.isfinite(x) else f"{x:.4f}"  # noqa: E731
    for r in rows:
        stats = [num(v) for n in RECALL_NS for v in r[f"R@{n}"]]
        writer.writerow(
            [
                r["aggregator"],
                r["mask"],
                r["backbone"],
                r["n"],
                " ".join(map(str, r["seeds"])),
                *stats,
                num(r["wall_time_s"]),
                r["failed"],
                _epochs(r["best_epochs"], " "),
                str(partial).lower(),
            ]
        )
    return buf.getvalue()


def _r1_by_seed(sweep: Sweep, cell: str, backbone: str) -> dict[int | None, float]:
    """Test R@1 of one row's finished runs, by seed."""
    return {j.seed: j.recall(1) for j in sweep.jobs_of(cell, backbone) if j.ok and math.isfinite(j.recall(1))}


def _paired_summary(
    sweep: Sweep, cell: str, backbone: str, reference: dict[int | None, float], label: str | None = None
) -> str | None:
    """ "<row> +g ± s (better in k of n seeds)" for R@1 minus the reference's with the same seed.

    Runs with the same seed share the backbone init and the data, so the per-seed difference is
    the fair comparison; its spread is much smaller than the seeds' spread of absolute recall.
    """
    diffs = [r1 - reference[seed] for seed, r1 in _r1_by_seed(sweep, cell, backbone).items() if seed in reference]
    if not diffs:
        return None
    mean, std = mean_std(diffs)
    spread = f" ± {_fmt(std)}" if math.isfinite(std) else ""
    better = sum(d > 0 for d in diffs)
    name = md_cell(label or sweep.label(cell))
    return f"{name} {_fmt(mean, signed=True)}{spread} (better in {better} of {len(diffs)} seeds)"


def _join(parts: list[str | None]) -> str:
    return ", ".join(p for p in parts if p)


def _baseline_gains(sweep: Sweep, backbone: str) -> str | None:
    """R@1 of every row minus the baseline aggregator without a mask, same seed; None when other rows
    finished but that reference did not, "" when there is nothing to compare."""
    if sweep.baseline is None:
        return ""
    reference = cell_name(sweep.baseline, NO_MASK)
    base = _r1_by_seed(sweep, reference, backbone)
    if not base:
        return None if any(j.ok for c in sweep.cells for j in sweep.jobs_of(c, backbone)) else ""
    return _join([_paired_summary(sweep, c, backbone, base) for c in sweep.cells if c != reference])


def _mask_gains(sweep: Sweep, backbone: str, aggregator: str) -> str:
    """R@1 of each mask minus no mask, same aggregator and seed (binary weights against binary)."""
    none = _r1_by_seed(sweep, cell_name(aggregator, NO_MASK), backbone)
    parts = [
        _paired_summary(sweep, cell_name(aggregator, m), backbone, none, label=sweep.mask_label(m))
        for m in sweep.masks
        if m != NO_MASK
    ]
    return _join(parts) if none else ""


def _learned_gains(sweep: Sweep, backbone: str) -> str:
    """R@1 of each learned-weights row minus the same row with binary weights, same seed."""
    return _join(
        [
            _paired_summary(sweep, c, backbone, _r1_by_seed(sweep, c.removesuffix(LEARNED), backbone))
            for c in sweep.cells
            if c.endswith(LEARNED)
        ]
    )


def _matrix(sweep: Sweep, backbone: str) -> list[str]:
    """Aggregator rows × mask columns of R@1 / R@5 mean ± std, then each mask's paired gain over none."""
    aggregators = [
        a for a in sweep.aggregators if any(j.aggregator == a and j.backbone == backbone for j in sweep.jobs)
    ]
    masks = [m for m in sweep.masks if any(j.mask == m and j.backbone == backbone for j in sweep.jobs)]
    out = [
        f"## Aggregator × mask ({md_cell(backbone)})",
        "",
        "R@1 / R@5 in %, mean ± std over seeds.",
        "",
        "| aggregator | " + " | ".join(md_cell(sweep.mask_label(m)) for m in masks) + " |",
        "|---|" + "---:|" * len(masks),
    ]
    for a in aggregators:
        cells = []
        for m in masks:
            ok = [j for j in sweep.jobs_of(cell_name(a, m), backbone) if j.ok]
            stats = [mean_std([j.recall(n) for j in ok]) for n in (1, 5)]
            cells.append(" / ".join(f"{_fmt(mu)} ± {_fmt(sd)}" for mu, sd in stats) if ok else "–")
        out.append(f"| {md_cell(a)} | " + " | ".join(cells) + " |")
    out.append("")
    gains = [(a, _mask_gains(sweep, backbone, a)) for a in aggregators]
    if any(g for _, g in gains):
        out += ["**R@1 gain of each mask over `none`, same aggregator**, paired by seed, mean ± std:", ""]
        out += [f"- {md_cell(a)}: {g}" for a, g in gains if g] + [""]
    return out


def _class_weight_table(sweep: Sweep) -> list[str]:
    """Markdown table of the learned class weights, mean ± std over seeds, one column per row of the sweep."""
    cells = sweep.learned_weights()
    if not cells:
        return []
    columns = list(cells)
    classes = list(next(iter(cells.values()))[0])
    out = [
        "## Learned class weights",
        "",
        "w_c = sigmoid(θ_c) after training (start: 0.98 static classes, 0.02 the others), mean ± std over seeds.",
        "",
        "| class | " + " | ".join(f"{md_cell(c.removesuffix(LEARNED))} ({md_cell(bb)})" for bb, c in columns) + " |",
        "|---|" + "---:|" * len(columns),
    ]
    for name in classes:
        stats = [mean_std([float(w[name]) for w in cells[c] if name in w]) for c in columns]
        out.append(
            f"| {md_cell(name)} | "
            + " | ".join(f"{m:.2f} ± {s:.2f}" if math.isfinite(s) else f"{m:.2f}" for m, s in stats)
            + " |"
        )
    return out + [""]


def _markdown(sweep: Sweep, rows: list[dict[str, Any]], figures: dict[str, str | None]) -> str:
    """Human-readable report: table, matrix, paired R@1 gains, failed jobs, figures."""
    n_ok, n_unfinished = sum(j.ok for j in sweep.jobs), len(sweep.unfinished)
    given = len(sweep.jobs) + len(sweep.not_started)
    counts = f"{given} jobs, {n_ok} ok, {len(sweep.jobs) - n_ok - n_unfinished} failed"
    if not sweep.complete:
        counts = (
            f"**Incomplete:** {counts}, {n_unfinished} did not finish, {len(sweep.not_started)} never started "
            "(the sweep was stopped, or a job's process was killed or has not ended yet); the rows hold only "
            "the jobs that finished"
        )
    out = [
        "# semvpr sweep results",
        "",
        f"{counts}. Recall@N in %, mean ± sample std over seeds.",
        "",
        "| backbone | aggregator · mask | R@1 | R@5 | R@10 | R@20 | runs ok | seeds | best epoch (val) | failed "
        "| wall time (s) |",
        "|---|---|---:|---:|---:|---:|---:|---|---|---:|---:|",
    ]
    for r in rows:
        cells = [f"{_fmt(r[f'R@{n}'][0])} ± {_fmt(r[f'R@{n}'][1])}" if r["n"] else "failed" for n in RECALL_NS]
        out.append(
            f"| {md_cell(r['backbone'])} | {md_cell(sweep.label(r['cell']))} | {' | '.join(cells)} | {r['n']} | "
            f"{', '.join(map(str, r['seeds'])) or '–'} | {_epochs(r['best_epochs'], ', ') or '–'} | {r['failed']} | "
            f"{_fmt(r['wall_time_s'])} |"
        )
    out.append("")
    reference = md_cell(sweep.label(cell_name(sweep.baseline, NO_MASK))) if sweep.baseline else ""
    for bb in sweep.backbones:
        gains = _baseline_gains(sweep, bb)
        if gains is None:
            out += [f"**R@1 gain over {reference} ({md_cell(bb)}):** no finished {reference} run to compare with.", ""]
        elif gains:
            out += [
                f"**R@1 gain over {reference} ({md_cell(bb)})**, per seed (same backbone init and data), then "
                f"mean ± std: {gains}",
                "",
            ]
        learned = _learned_gains(sweep, bb)
        if learned:
            out += [
                f"**R@1 gain of learned class weights over binary weights ({md_cell(bb)})**, paired by seed: {learned}",
                "",
            ]
    for bb in sweep.backbones:
        out += _matrix(sweep, bb)
    out += _class_weight_table(sweep)
    failed = [j for j in sweep.jobs if not j.ok]
    if failed:
        out += ["## Failed jobs", ""]
        out += [
            f"- `{md_cell(j.name)}` ({md_cell(j.cell)}, {md_cell(j.backbone)}, "
            f"seed {j.seed if j.seed is not None else '?'}): "
            f"{md_cell(j.error)}"
            for j in failed
        ]
    if sweep.not_started:
        out += ["", "## Jobs not started", ""] if failed else ["## Jobs not started", ""]
        out += [f"- `{md_cell(' '.join(job))}`" for job in sweep.not_started]
    out += ["", "## Figures", ""] if failed or sweep.not_started else ["## Figures", ""]
    for fname, skipped in figures.items():  # blank-line separated so each image renders as its own block
        out += [f"- `{fname}` skipped: {md_cell(skipped)}" if skipped else f"![{fname}]({fname})", ""]
    return "\n".join(out).rstrip() + "\n"


#: Every figure a report may draw.
FIGURES = ("recall_at_n.png", "r1_by_aggregator.png", "figure3.png", "retrievals.png", "class_weights.png")


def write_report(sweep_dir: str | Path, partial: bool = False) -> Path:
    """Write results.csv, results.md and the figures into sweep_dir; return the results.md path.
    ``partial``: the sweep is still running: the table of the jobs finished so far, marked as such, and no
    figures (they are drawn when the sweep ends).

    Everything is made in a fresh scratch directory first and moved in only when all of it was
    made, so a failure leaves the previous report whole (never a new csv beside an old md).
    """
    from semvpr.reporting import figures as plots  # matplotlib is only needed here, not to import the callback

    sweep = load_sweep(sweep_dir, finished_only=partial)
    rows = _rows(sweep)
    figures: dict[str, str | None] = {}
    drawings = [
        ("recall_at_n.png", plots.recall_curves),
        ("r1_by_aggregator.png", plots.matrix_bars),
        ("figure3.png", plots.figure3),
        ("retrievals.png", plots.retrievals),
    ]
    if any(numeric_weights(j.metrics.get("class_weights")) for j in sweep.jobs):
        drawings.append(("class_weights.png", plots.class_weights))
    if partial:
        drawings = []
    names = [fname for fname, _ in drawings] + ["results.csv", "results.md"]
    for name in names:  # every target is checked before anything is made or moved
        check_replaceable(sweep.dir / name)
    scratch = temp_dir(sweep.dir, "report")
    try:
        for fname, draw in drawings:
            try:
                figures[fname] = draw(sweep, scratch / fname)
            except Exception as err:  # one broken figure must not cost the table
                figures[fname] = f"{type(err).__name__}: {err}"
        write_text(scratch / "results.csv", _csv_text(rows, partial or not sweep.complete))
        text = _markdown(sweep, rows, figures)
        if partial:
            title, _, rest = text.partition("\n")
            note = (
                f"**Partial: the sweep is still running.** {len(sweep.jobs)} job(s) finished so far; this table "
                "is rewritten as each job ends, and the figures are drawn when the sweep ends."
            )
            text = f"{title}\n\n{note}\n{rest}"
        write_text(scratch / "results.md", text)
        made = sorted(scratch.iterdir(), key=lambda p: p.name == "results.md")  # the md last
        for path in made:
            os.replace(path, sweep.dir / path.name)
        if not partial:  # an earlier report's figure this one did not draw would stand beside it as if it had
            for stale in set(FIGURES) - {p.name for p in made}:
                (sweep.dir / stale).unlink(missing_ok=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return sweep.dir / "results.md"


def print_summary(md: Path) -> None:
    """Print where the report is and its table."""
    print(f"semvpr report: {md}")
    lines = md.read_text(encoding="utf-8").splitlines()
    print(terminal_text(ln for ln in lines if ln.startswith(("|", "**R@1", "**Incomplete", "- "))))

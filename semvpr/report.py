"""Sweep-end report: results.csv / results.md and figures, read back from the per-run files of a multirun."""
from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from semvpr.errors import SemvprError, exit_on_user_error
from semvpr.io import write_text
from semvpr.metrics import RECALL_NS

LEARNED = "+learned"  # a mask run with mask.weights=learned is reported as "<mask>+learned"
NO_MASK = "none"  # the mask choice every other mask is paired against


@dataclass
class Job:
    """One run of the sweep as read back from its directory."""

    dir: Path
    name: str
    aggregator: str
    mask: str  # the mask choice, with LEARNED appended for learned class weights
    backbone: str
    seed: int | None
    ok: bool
    error: str
    metrics: dict[str, Any]
    #: Dataset roots the run recorded (data.root, paths.cache_dir): the only places images are drawn from.
    roots: tuple[Path, ...] = ()

    @property
    def cell(self) -> str:
        """The table row this run belongs to (besides its backbone): aggregator · mask."""
        return cell_name(self.aggregator, self.mask)

    def recall(self, n: int) -> float:
        """Test Recall@n in percent (nan when the run did not record it)."""
        value = self.metrics.get(f"test/R@{n}")
        return float(value) if isinstance(value, (int, float)) else math.nan


def cell_name(aggregator: str, mask: str) -> str:
    """Display key of an (aggregator, mask) pair."""
    return f"{aggregator} · {mask}"


@dataclass
class Sweep:
    """All jobs of one sweep directory, with the orderings the tables and figures share.

    Runs are grouped by what they recorded (aggregator, mask, mask weighting, backbone), never by
    a name known here: the baseline aggregator and the upper-bound masks are flags in metrics.json.
    """

    dir: Path
    jobs: list[Job]

    @property
    def backbones(self) -> list[str]:
        """Backbones in a stable (alphabetical) order, unknown ones last."""
        return sorted({j.backbone for j in self.jobs}, key=lambda b: (b == "?", b))

    @property
    def baseline(self) -> str | None:
        """The aggregator a run recorded as the baseline (conf/aggregator: baseline: true), if any ran."""
        names = sorted({j.aggregator for j in self.jobs if j.metrics.get("baseline_aggregator") is True})
        return names[0] if names else None

    @property
    def upper_bounds(self) -> frozenset[str]:
        """Masks recorded as upper bounds (ground truth: a ceiling to read against, not a competitor)."""
        return frozenset(j.mask.removesuffix(LEARNED) for j in self.jobs if j.metrics.get("mask_upper_bound") is True)

    @property
    def aggregators(self) -> list[str]:
        """The baseline aggregator first, then the others alphabetically, unknown last."""
        return sorted({j.aggregator for j in self.jobs}, key=lambda a: (a != self.baseline, a == "?", a))

    @property
    def masks(self) -> list[str]:
        """No mask first, upper bounds last, each mask's learned-weights variant right after it."""
        bounds = self.upper_bounds
        return sorted({j.mask for j in self.jobs}, key=lambda m: (
            m.removesuffix(LEARNED) != NO_MASK, m.removesuffix(LEARNED) in bounds, m == "?",
            m.removesuffix(LEARNED), m.endswith(LEARNED)))

    @property
    def cells(self) -> list[str]:
        """Rows in reading order: aggregators outer, masks inner."""
        present = {j.cell for j in self.jobs}
        return [c for a in self.aggregators for m in self.masks if (c := cell_name(a, m)) in present]

    def label(self, cell: str) -> str:
        """Display name of a row."""
        mask = cell.rpartition(" · ")[2].removesuffix(LEARNED)
        return f"{cell} (upper bound)" if mask in self.upper_bounds else cell

    def jobs_of(self, cell: str, backbone: str, needs: str | None = None) -> list[Job]:
        """Jobs of one row, ok runs first then by seed, optionally only those holding file `needs`."""
        jobs = [j for j in self.jobs if j.cell == cell and j.backbone == backbone]
        jobs = [j for j in jobs if needs is None or (j.dir / needs).is_file()]
        return sorted(jobs, key=lambda j: (not j.ok, j.seed if j.seed is not None else math.inf, j.name))

    def learned_weights(self) -> dict[tuple[str, str], list[dict[str, float]]]:
        """Per (backbone, row), the learned class weights of each ok run, in table order."""
        runs: dict[tuple[str, str], list[dict[str, float]]] = {}
        for job in self.jobs:
            weights = numeric_weights(job.metrics.get("class_weights")) if job.ok else None
            if weights is not None:
                runs.setdefault((job.backbone, job.cell), []).append(weights)
        return {c: runs[c] for c in sorted(runs, key=lambda c: (c[0], self.cells.index(c[1])))}

    def image_path(self, stored: str) -> Path | None:
        """Find an image path stored by a run (relative paths are relative to the run's launch dir);
        None unless it lies under a dataset root some job recorded (a sweep directory is data)."""
        path = Path(stored)
        # The launch dir is usually the project root, an ancestor of outputs/multiruns/<date>/<time>.
        candidates = [path] if path.is_absolute() else [r / path for r in (Path.cwd(), self.dir, *self.dir.resolve().parents)]
        roots = {root.resolve() for job in self.jobs for root in job.roots}
        for candidate in candidates:
            if candidate.is_file() and any(candidate.resolve().is_relative_to(root) for root in roots):
                return candidate
        return None


def md_cell(text: object) -> str:
    """Text from a run as one markdown table cell or list item: no HTML tag or entity ('&', '<'
    escaped), no '|', '`' or line break."""
    flat = " ".join(str(text).split())
    return flat.replace("&", "&amp;").replace("<", "&lt;").replace("|", "&#124;").replace("`", "&#96;")


def numeric_weights(value: object) -> dict[str, float] | None:
    """A run's recorded class weights if they are a name -> finite number mapping, else None."""
    if not isinstance(value, dict) or not value:
        return None
    ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value.values())
    return {str(k): float(v) for k, v in value.items()} if ok else None


def _error_line(error: object) -> str:
    """The telling line of an error: a traceback ends with the exception, so take the last line."""
    lines = [ln.strip() for ln in str(error or "").splitlines() if ln.strip()]
    return lines[-1][:200] if lines else ""


FACT_KEYS = ("aggregator", "mask", "backbone", "seed", "mask.weights")


def _yaml(path: Path) -> Any:
    """A .hydra file as plain YAML data: interpolations stay text, nothing is resolved."""
    return yaml.safe_load(path.read_text(encoding="utf-8")) if path.is_file() else None


def _select(node: Any, dotted: str) -> Any:
    for key in dotted.split("."):
        node = node.get(key) if isinstance(node, dict) else None
    return node


def _hydra_facts(job_dir: Path) -> tuple[dict[str, str], tuple[Path, ...]]:
    """aggregator / mask / backbone / seed / mask weighting of a job from its .hydra files (for jobs that
    died before metrics.json), read as plain YAML (nothing resolved), and the dataset roots it recorded.
    The composed choices are used, so a filter preset counts as the aggregator and mask it chose."""
    # lowest priority: the dir name itself, Hydra's override_dirname "aggregator=gem,mask=student,seed=1"
    facts = {k: v for k, _, v in (item.partition("=") for item in job_dir.name.split(",")) if k in FACT_KEYS and v}
    hydra_dir = job_dir / ".hydra"
    roots: list[Path] = []
    try:
        config, hydra_cfg = _yaml(hydra_dir / "config.yaml"), _yaml(hydra_dir / "hydra.yaml")
        # mask.weights is usually "${filter.weights}" (text here): the preset's value stands for it.
        for key, fact in (("seed", "seed"), ("filter.weights", "mask.weights"), ("mask.weights", "mask.weights")):
            value = _select(config, key)
            if value is not None and "${" not in str(value):
                facts[fact] = str(value)
        choices = _select(hydra_cfg, "hydra.runtime.choices")
        for key in ("aggregator", "mask", "backbone"):
            if isinstance(choices, dict) and choices.get(key) is not None:
                facts[key] = str(choices[key])
        for item in _yaml(hydra_dir / "overrides.yaml") or []:
            key, _, value = str(item).lstrip("+~").partition("=")
            key = "mask.weights" if key == "filter.weights" else key
            if key in FACT_KEYS:
                facts[key] = value
        launch = Path(str(_select(hydra_cfg, "hydra.runtime.cwd") or Path.cwd()))
        for key in ("data.root", "paths.cache_dir"):
            value = _select(config, key)
            if isinstance(value, str) and value and "${" not in value:
                roots.append(launch / Path(value).expanduser())
    except Exception:  # a damaged .hydra dir only costs us labels and images, never the report
        pass
    return facts, tuple(roots)


def read_job(job_dir: Path, sweep_dir: Path) -> Job:
    """Read one job directory; a missing or unreadable metrics.json makes a failed job."""
    rel = job_dir.relative_to(sweep_dir).as_posix()
    name = job_dir.name if rel == "." else rel
    metrics: dict[str, Any] = {}
    error = ""
    path = job_dir / "metrics.json"
    if not path.is_file():
        error = "no metrics.json"
    else:
        try:
            loaded = json.loads(path.read_text(encoding="utf-8"))
            metrics = loaded if isinstance(loaded, dict) else {}
            error = "" if metrics else "metrics.json is not a JSON object"
        except (OSError, ValueError) as err:
            error = f"unreadable metrics.json ({err})"
    ok = not error and metrics.get("status") == "ok"
    if not ok and not error:
        error = _error_line(metrics.get("error")) or f"status {metrics.get('status')!r}"
    facts, roots = _hydra_facts(job_dir)
    seed = metrics.get("seed", facts.get("seed"))
    try:
        seed = int(seed) if seed is not None else None
    except ValueError:
        seed = None
    mask = str(metrics.get("mask") or facts.get("mask") or "?")
    if (metrics.get("weights") or facts.get("mask.weights")) == "learned":
        mask += LEARNED
    return Job(job_dir, name, str(metrics.get("aggregator") or facts.get("aggregator") or "?"), mask,
               str(metrics.get("backbone") or facts.get("backbone") or "?"), seed, ok, error, metrics,
               roots)


def load_sweep(sweep_dir: Path) -> Sweep:
    """Discover job dirs (any dir holding metrics.json or a .hydra dir) and read them."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise SemvprError(f"sweep dir {sweep_dir} does not exist; pass the multirun dir, e.g. outputs/multiruns/<date>/<time>")
    dirs = {p.parent for p in sweep_dir.rglob("metrics.json")}
    dirs |= {p.parent for p in sweep_dir.rglob(".hydra") if p.is_dir()}
    if not dirs:
        raise SemvprError(f"no job dirs in {sweep_dir} (none holds metrics.json or .hydra/); "
                          "pass the multirun dir written by `python -m semvpr.train -m ...`")
    return Sweep(sweep_dir, [read_job(d, sweep_dir) for d in sorted(dirs)])


def mean_std(values: list[float]) -> tuple[float, float]:
    """Mean and sample std (ddof=1) of the finite values; std is nan for fewer than two."""
    vals = np.array([v for v in values if math.isfinite(v)], dtype=np.float64)
    if vals.size == 0:
        return math.nan, math.nan
    return float(vals.mean()), float(vals.std(ddof=1)) if vals.size > 1 else math.nan


def _rows(sweep: Sweep) -> list[dict[str, Any]]:
    """One aggregated row per (backbone, aggregator, mask), backbones outer, rows in reading order."""
    rows = []
    for bb in sweep.backbones:
        for cell in sweep.cells:
            jobs = sweep.jobs_of(cell, bb)
            if not jobs:
                continue
            ok = [j for j in jobs if j.ok]
            row: dict[str, Any] = {"cell": cell, "aggregator": jobs[0].aggregator, "mask": jobs[0].mask,
                                   "backbone": bb, "n": len(ok), "failed": len(jobs) - len(ok),
                                   "seeds": sorted(j.seed for j in ok if j.seed is not None)}
            for n in RECALL_NS:
                row[f"R@{n}"] = mean_std([j.recall(n) for j in ok])
            walls = [float(j.metrics["wall_time_s"]) for j in ok if isinstance(j.metrics.get("wall_time_s"), (int, float))]
            row["wall_time_s"] = mean_std(walls)[0]
            rows.append(row)
    return rows


def _fmt(x: float, signed: bool = False) -> str:
    """One decimal; a typographic minus so signed gains read as −2.0 / +3.1."""
    if not math.isfinite(x):
        return "–"
    return (f"{x:+.1f}" if signed else f"{x:.1f}").replace("-", "−")


def _csv_text(rows: list[dict[str, Any]]) -> str:
    """Machine-readable table: means and stds unrounded-enough (4 decimals), blanks for missing."""
    buf = io.StringIO()
    cols = (["aggregator", "mask", "backbone", "n", "seeds"] + [f"R@{n}_{s}" for n in RECALL_NS for s in ("mean", "std")]
            + ["wall_time_s", "failed"])
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(cols)
    num = lambda x: "" if not math.isfinite(x) else f"{x:.4f}"  # noqa: E731
    for r in rows:
        stats = [num(v) for n in RECALL_NS for v in r[f"R@{n}"]]
        writer.writerow([r["aggregator"], r["mask"], r["backbone"], r["n"], " ".join(map(str, r["seeds"])), *stats,
                         num(r["wall_time_s"]), r["failed"]])
    return buf.getvalue()


def _r1_by_seed(sweep: Sweep, cell: str, backbone: str) -> dict[int | None, float]:
    """Test R@1 of one row's finished runs, by seed."""
    return {j.seed: j.recall(1) for j in sweep.jobs_of(cell, backbone) if j.ok and math.isfinite(j.recall(1))}


def _paired_summary(sweep: Sweep, cell: str, backbone: str, reference: dict[int | None, float],
                    label: str | None = None) -> str | None:
    """"<row> +g ± s (better in k of n seeds)" for R@1 minus the reference's with the same seed.

    Runs with the same seed share the backbone init and the data, so the per-seed difference is
    the fair comparison; its spread is much smaller than the seeds' spread of absolute recall.
    """
    diffs = [r1 - reference[seed] for seed, r1 in _r1_by_seed(sweep, cell, backbone).items() if seed in reference]
    if not diffs:
        return None
    mean, std = mean_std(diffs)
    spread = f" ± {_fmt(std)}" if math.isfinite(std) else ""
    better = sum(d > 0 for d in diffs)
    return f"{md_cell(label or sweep.label(cell))} {_fmt(mean, signed=True)}{spread} (better in {better} of {len(diffs)} seeds)"


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
    parts = [_paired_summary(sweep, cell_name(aggregator, m), backbone, none, label=sweep.label(m))
             for m in sweep.masks if m != NO_MASK]
    return _join(parts) if none else ""


def _learned_gains(sweep: Sweep, backbone: str) -> str:
    """R@1 of each learned-weights row minus the same row with binary weights, same seed."""
    return _join([_paired_summary(sweep, c, backbone, _r1_by_seed(sweep, c.removesuffix(LEARNED), backbone))
                  for c in sweep.cells if c.endswith(LEARNED)])


def _matrix(sweep: Sweep, backbone: str) -> list[str]:
    """Aggregator rows × mask columns of R@1 / R@5 mean ± std, then each mask's paired gain over none."""
    aggregators = [a for a in sweep.aggregators if any(j.aggregator == a and j.backbone == backbone for j in sweep.jobs)]
    masks = [m for m in sweep.masks if any(j.mask == m and j.backbone == backbone for j in sweep.jobs)]
    out = [f"## Aggregator × mask ({md_cell(backbone)})", "", "R@1 / R@5 in %, mean ± std over seeds.", "",
           "| aggregator | " + " | ".join(md_cell(sweep.label(m)) for m in masks) + " |", "|---|" + "---:|" * len(masks)]
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
    out = ["## Learned class weights", "",
           "w_c = sigmoid(θ_c) after training (start: 0.98 static classes, 0.02 the others), mean ± std over seeds.", "",
           "| class | " + " | ".join(f"{md_cell(c.removesuffix(LEARNED))} ({md_cell(bb)})" for bb, c in columns) + " |",
           "|---|" + "---:|" * len(columns)]
    for name in classes:
        stats = [mean_std([float(w[name]) for w in cells[c] if name in w]) for c in columns]
        out.append(f"| {md_cell(name)} | " + " | ".join(f"{m:.2f} ± {s:.2f}" if math.isfinite(s) else f"{m:.2f}"
                                              for m, s in stats) + " |")
    return out + [""]


def _markdown(sweep: Sweep, rows: list[dict[str, Any]], figures: dict[str, str | None]) -> str:
    """Human-readable report: table, matrix, paired R@1 gains, failed jobs, figures."""
    n_ok = sum(j.ok for j in sweep.jobs)
    out = ["# semvpr sweep results", "",
           f"Sweep `{md_cell(sweep.dir)}`: {len(sweep.jobs)} jobs, {n_ok} ok, {len(sweep.jobs) - n_ok} failed. "
           "Recall@N in %, mean ± sample std over seeds.", "",
           "| backbone | aggregator · mask | R@1 | R@5 | R@10 | R@20 | runs ok | seeds | failed | wall time (s) |",
           "|---|---|---:|---:|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        cells = [f"{_fmt(r[f'R@{n}'][0])} ± {_fmt(r[f'R@{n}'][1])}" if r["n"] else "failed" for n in RECALL_NS]
        out.append(f"| {md_cell(r['backbone'])} | {md_cell(sweep.label(r['cell']))} | {' | '.join(cells)} | {r['n']} | "
                   f"{', '.join(map(str, r['seeds'])) or '–'} | {r['failed']} | {_fmt(r['wall_time_s'])} |")
    out.append("")
    reference = f"`{cell_name(sweep.baseline, NO_MASK)}`" if sweep.baseline else ""
    for bb in sweep.backbones:
        gains = _baseline_gains(sweep, bb)
        if gains is None:
            out += [f"**R@1 gain over {reference} ({md_cell(bb)}):** no finished {reference} run to compare with.", ""]
        elif gains:
            out += [f"**R@1 gain over {reference} ({md_cell(bb)})**, per seed (same backbone init and data), then "
                    f"mean ± std: {gains}", ""]
        learned = _learned_gains(sweep, bb)
        if learned:
            out += [f"**R@1 gain of learned class weights over binary weights ({md_cell(bb)})**, paired by seed: {learned}", ""]
    for bb in sweep.backbones:
        out += _matrix(sweep, bb)
    out += _class_weight_table(sweep)
    failed = [j for j in sweep.jobs if not j.ok]
    if failed:
        out += ["## Failed jobs", ""]
        out += [f"- `{md_cell(j.name)}` ({md_cell(j.cell)}, {md_cell(j.backbone)}, seed {j.seed if j.seed is not None else '?'}): "
                f"{md_cell(j.error)}"
                for j in failed]
    out += ["", "## Figures", ""] if failed else ["## Figures", ""]
    for fname, skipped in figures.items():  # blank-line separated so each image renders as its own block
        out += [f"- `{fname}` skipped: {md_cell(skipped)}" if skipped else f"![{fname}]({fname})", ""]
    return "\n".join(out).rstrip() + "\n"


def write_report(sweep_dir: Path) -> Path:
    """Write results.csv, results.md and the figures into sweep_dir; return the results.md path.

    Everything is made in a fresh scratch directory first and moved in only when all of it was
    made, so a failure leaves the previous report whole (never a new csv beside an old md).
    """
    from semvpr import plots  # matplotlib is only needed here, not to import the callback

    sweep = load_sweep(Path(sweep_dir))
    rows = _rows(sweep)
    figures: dict[str, str | None] = {}
    drawings = [("recall_at_n.png", plots.recall_curves), ("r1_by_aggregator.png", plots.matrix_bars),
                ("figure3.png", plots.figure3), ("retrievals.png", plots.retrievals)]
    if any(numeric_weights(j.metrics.get("class_weights")) for j in sweep.jobs):
        drawings.append(("class_weights.png", plots.class_weights))
    scratch = Path(tempfile.mkdtemp(prefix=".report.", suffix=".tmp", dir=sweep.dir))
    try:
        for fname, draw in drawings:
            try:
                figures[fname] = draw(sweep, scratch / fname)
            except Exception as err:  # one broken figure must not cost the table
                figures[fname] = f"{type(err).__name__}: {err}"
        write_text(scratch / "results.csv", _csv_text(rows))
        write_text(scratch / "results.md", _markdown(sweep, rows, figures))
        for made in sorted(scratch.iterdir(), key=lambda p: p.name == "results.md"):  # the md last
            os.replace(made, sweep.dir / made.name)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return sweep.dir / "results.md"


def print_summary(md: Path) -> None:
    """Print where the report is and its table."""
    print(f"semvpr report: {md}")
    print("\n".join(ln for ln in md.read_text(encoding="utf-8").splitlines() if ln.startswith(("|", "**R@1", "- "))))


def sweep_dir_of(config: DictConfig) -> Path:
    """A multirun's sweep dir (hydra.sweep.dir, relative to the launch dir)."""
    sweep_dir = Path(str(config.hydra.sweep.dir))
    if not sweep_dir.is_absolute():
        sweep_dir = Path(OmegaConf.select(config, "hydra.runtime.cwd", default=None) or os.getcwd()) / sweep_dir
    return sweep_dir


class ReportCallback(Callback):
    """Hydra callback: write the report when a multirun ends (hydra.callbacks.report._target_)."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Report on config.hydra.sweep.dir; never raise, the runs' own files are the results."""
        where = "the sweep dir"
        try:
            sweep_dir = sweep_dir_of(config)
            where = str(sweep_dir)
            print_summary(write_report(sweep_dir))
        except Exception as err:
            print(f"semvpr: report failed for {where} ({type(err).__name__}: {err}); "
                  f"rerun with `python -m semvpr.report {where}`", file=sys.stderr)


@exit_on_user_error
def main(argv: list[str] | None = None) -> int:
    """CLI: python -m semvpr.report <sweep dir>."""
    parser = argparse.ArgumentParser(prog="python -m semvpr.report",
                                     description="Write results.csv/.md and figures for a finished sweep.")
    parser.add_argument("sweep_dir", type=Path, help="multirun dir, e.g. outputs/multiruns/<date>/<time>")
    print_summary(write_report(parser.parse_args(argv).sweep_dir))
    return 0


if __name__ == "__main__":
    main()

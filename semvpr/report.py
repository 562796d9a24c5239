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

FILTER_ORDER = ("none", "attention", "unet", "mask2former")
UPPER_BOUNDS = frozenset({"oracle"})  # ground-truth masks: a ceiling to read against, not a competitor


@dataclass
class Job:
    """One run of the sweep as read back from its directory."""

    dir: Path
    name: str
    filter: str
    backbone: str
    seed: int | None
    ok: bool
    error: str
    metrics: dict[str, Any]
    #: Dataset roots the run recorded (data.root, paths.cache_dir): the only places images are drawn from.
    roots: tuple[Path, ...] = ()

    def recall(self, n: int) -> float:
        """Test Recall@n in percent (nan when the run did not record it)."""
        value = self.metrics.get(f"test/R@{n}")
        return float(value) if isinstance(value, (int, float)) else math.nan


@dataclass
class Sweep:
    """All jobs of one sweep directory, with the orderings the table and figures share."""

    dir: Path
    jobs: list[Job]

    @property
    def backbones(self) -> list[str]:
        """Backbones in a stable (alphabetical) order, unknown ones last."""
        return sorted({j.backbone for j in self.jobs}, key=lambda b: (b == "?", b))

    @property
    def filters(self) -> list[str]:
        """Filters in reading order: the seed's four, then extras, upper bounds last."""
        return sorted({j.filter for j in self.jobs}, key=filter_rank)

    def label(self, name: str) -> str:
        """Display name of a filter."""
        return f"{name} (upper bound)" if name.removesuffix(LEARNED) in UPPER_BOUNDS else name

    def jobs_of(self, filter_: str, backbone: str, needs: str | None = None) -> list[Job]:
        """Jobs of one cell, ok runs first then by seed, optionally only those holding file `needs`."""
        jobs = [j for j in self.jobs if j.filter == filter_ and j.backbone == backbone]
        jobs = [j for j in jobs if needs is None or (j.dir / needs).is_file()]
        return sorted(jobs, key=lambda j: (not j.ok, j.seed if j.seed is not None else math.inf, j.name))

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


LEARNED = "+learned"  # a filter run with filter.weights=learned is reported as "<filter>+learned"


def filter_rank(name: str) -> tuple[int, str, bool]:
    """Sort key placing none, attention, unet, mask2former first and upper bounds last, each filter's
    learned-weights variant right after it."""
    base, learned = name.removesuffix(LEARNED), name.endswith(LEARNED)
    if base in FILTER_ORDER:
        return FILTER_ORDER.index(base), "", learned
    return len(FILTER_ORDER) + (base in UPPER_BOUNDS), base, learned


def cell(text: object) -> str:
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


def _yaml(path: Path) -> Any:
    """A .hydra file as plain YAML data: interpolations stay text, nothing is resolved."""
    return yaml.safe_load(path.read_text(encoding="utf-8")) if path.is_file() else None


def _select(node: Any, dotted: str) -> Any:
    for key in dotted.split("."):
        node = node.get(key) if isinstance(node, dict) else None
    return node


def _hydra_facts(job_dir: Path) -> tuple[dict[str, str], tuple[Path, ...]]:
    """filter / backbone / seed of a job from its .hydra files (for jobs that died before metrics.json),
    and the dataset roots it recorded."""
    # lowest priority: the dir name itself, Hydra's override_dirname "backbone=vgg16,filter=unet,seed=1"
    facts = {k: v for k, _, v in (item.partition("=") for item in job_dir.name.split(","))
             if k in ("filter", "backbone", "seed", "filter.weights") and v}
    hydra_dir = job_dir / ".hydra"
    roots: list[Path] = []
    try:
        config, hydra_cfg = _yaml(hydra_dir / "config.yaml"), _yaml(hydra_dir / "hydra.yaml")
        if _select(config, "seed") is not None:
            facts["seed"] = str(_select(config, "seed"))
        choices = _select(hydra_cfg, "hydra.runtime.choices")
        for key in ("filter", "backbone"):
            if isinstance(choices, dict) and choices.get(key) is not None:
                facts[key] = str(choices[key])
        for item in _yaml(hydra_dir / "overrides.yaml") or []:
            key, _, value = str(item).lstrip("+~").partition("=")
            if key in ("filter", "backbone", "seed", "filter.weights"):
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
    filter_ = str(metrics.get("filter") or facts.get("filter") or "?")
    if (metrics.get("weights") or facts.get("filter.weights")) == "learned":
        filter_ += LEARNED
    return Job(job_dir, name, filter_, str(metrics.get("backbone") or facts.get("backbone") or "?"), seed, ok, error,
               metrics, roots)


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
    """One aggregated row per (backbone, filter), backbones outer, filters in reading order."""
    rows = []
    for bb in sweep.backbones:
        for f in sweep.filters:
            jobs = sweep.jobs_of(f, bb)
            if not jobs:
                continue
            ok = [j for j in jobs if j.ok]
            row: dict[str, Any] = {"filter": f, "backbone": bb, "n": len(ok), "failed": len(jobs) - len(ok),
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
    cols = ["filter", "backbone", "n", "seeds"] + [f"R@{n}_{s}" for n in RECALL_NS for s in ("mean", "std")] + ["wall_time_s", "failed"]
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(cols)
    num = lambda x: "" if not math.isfinite(x) else f"{x:.4f}"  # noqa: E731
    for r in rows:
        stats = [num(v) for n in RECALL_NS for v in r[f"R@{n}"]]
        writer.writerow([r["filter"], r["backbone"], r["n"], " ".join(map(str, r["seeds"])), *stats,
                         num(r["wall_time_s"]), r["failed"]])
    return buf.getvalue()


def _r1_by_seed(sweep: Sweep, filter_: str, backbone: str) -> dict[int | None, float]:
    """Test R@1 of one cell's finished runs, by seed."""
    return {j.seed: j.recall(1) for j in sweep.jobs_of(filter_, backbone) if j.ok and math.isfinite(j.recall(1))}


def _paired_summary(sweep: Sweep, filter_: str, backbone: str, reference: dict[int | None, float]) -> str | None:
    """"<filter> +g ± s (better in k of n seeds)" for R@1 minus the reference's with the same seed."""
    diffs = [r1 - reference[seed] for seed, r1 in _r1_by_seed(sweep, filter_, backbone).items() if seed in reference]
    if not diffs:
        return None
    mean, std = mean_std(diffs)
    spread = f" ± {_fmt(std)}" if math.isfinite(std) else ""
    better = sum(d > 0 for d in diffs)
    return f"{cell(sweep.label(filter_))} {_fmt(mean, signed=True)}{spread} (better in {better} of {len(diffs)} seeds)"


def _paired_gains(sweep: Sweep, backbone: str) -> str | None:
    """R@1 of each filter minus `none` with the same seed, summarised; None when other filters
    finished but `none` did not, "" when there is nothing to compare.

    Runs with the same seed share the backbone init and the data, so the per-seed difference is
    the fair comparison; its spread is much smaller than the seeds' spread of absolute recall.
    """
    none = _r1_by_seed(sweep, "none", backbone)
    if not none:
        return None if any(j.ok for f in sweep.filters for j in sweep.jobs_of(f, backbone)) else ""
    parts = [_paired_summary(sweep, f, backbone, none) for f in sweep.filters if f != "none"]
    return ", ".join(p for p in parts if p)


def _learned_gains(sweep: Sweep, backbone: str) -> str:
    """R@1 of each learned-weights filter minus its binary filter with the same seed."""
    parts = [_paired_summary(sweep, f, backbone, _r1_by_seed(sweep, f.removesuffix(LEARNED), backbone))
             for f in sweep.filters if f.endswith(LEARNED)]
    return ", ".join(p for p in parts if p)


def _class_weight_table(sweep: Sweep) -> list[str]:
    """Markdown table of the learned class weights, mean ± std over seeds, one column per filter."""
    cells: dict[tuple[str, str], list[dict[str, float]]] = {}
    for j in sweep.jobs:
        weights = numeric_weights(j.metrics.get("class_weights")) if j.ok else None
        if weights is not None:
            cells.setdefault((j.backbone, j.filter), []).append(weights)
    if not cells:
        return []
    columns = sorted(cells, key=lambda c: (c[0], filter_rank(c[1])))
    classes = list(next(iter(cells.values()))[0])
    out = ["## Learned class weights", "",
           "w_c = sigmoid(θ_c) after training (start: 0.98 static classes, 0.02 the others), mean ± std over seeds.", "",
           "| class | " + " | ".join(f"{cell(f.removesuffix(LEARNED))} ({cell(bb)})" for bb, f in columns) + " |",
           "|---|" + "---:|" * len(columns)]
    for name in classes:
        stats = [mean_std([float(w[name]) for w in cells[c] if name in w]) for c in columns]
        out.append(f"| {cell(name)} | " + " | ".join(f"{m:.2f} ± {s:.2f}" if math.isfinite(s) else f"{m:.2f}"
                                              for m, s in stats) + " |")
    return out + [""]


def _markdown(sweep: Sweep, rows: list[dict[str, Any]], figures: dict[str, str | None]) -> str:
    """Human-readable report: table, R@1 gains over `none`, failed jobs, figures."""
    n_ok = sum(j.ok for j in sweep.jobs)
    out = ["# semvpr sweep results", "",
           f"Sweep `{cell(sweep.dir)}`: {len(sweep.jobs)} jobs, {n_ok} ok, {len(sweep.jobs) - n_ok} failed. "
           "Recall@N in %, mean ± sample std over seeds.", "",
           "| backbone | filter | R@1 | R@5 | R@10 | R@20 | runs ok | seeds | failed | wall time (s) |",
           "|---|---|---:|---:|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        cells = [f"{_fmt(r[f'R@{n}'][0])} ± {_fmt(r[f'R@{n}'][1])}" if r["n"] else "failed" for n in RECALL_NS]
        out.append(f"| {cell(r['backbone'])} | {cell(sweep.label(r['filter']))} | {' | '.join(cells)} | {r['n']} | "
                   f"{', '.join(map(str, r['seeds'])) or '–'} | {r['failed']} | {_fmt(r['wall_time_s'])} |")
    out.append("")
    for bb in sweep.backbones:
        gains = _paired_gains(sweep, bb)
        if gains is None:
            out += [f"**R@1 gain over `none` ({cell(bb)}):** no finished `none` run to compare with.", ""]
        elif gains:
            out += [f"**R@1 gain over `none` ({cell(bb)})**, per seed (same backbone init and data), then "
                    f"mean ± std: {gains}", ""]
        learned = _learned_gains(sweep, bb)
        if learned:
            out += [f"**R@1 gain of learned class weights over the binary filter ({cell(bb)})**, paired by seed: "
                    f"{learned}", ""]
    out += _class_weight_table(sweep)
    failed = [j for j in sweep.jobs if not j.ok]
    if failed:
        out += ["## Failed jobs", ""]
        out += [f"- `{cell(j.name)}` ({cell(j.filter)}, {cell(j.backbone)}, seed {j.seed if j.seed is not None else '?'}): "
                f"{cell(j.error)}"
                for j in failed]
    out += ["", "## Figures", ""] if failed else ["## Figures", ""]
    for fname, skipped in figures.items():  # blank-line separated so each image renders as its own block
        out += [f"- `{fname}` skipped: {cell(skipped)}" if skipped else f"![{fname}]({fname})", ""]
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
    drawings = [("recall_at_n.png", plots.recall_curves), ("figure3.png", plots.figure3),
                ("retrievals.png", plots.retrievals)]
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
    print("\n".join(ln for ln in md.read_text(encoding="utf-8").splitlines() if ln.startswith(("|", "**R@1"))))


class ReportCallback(Callback):
    """Hydra callback: write the report when a multirun ends (hydra.callbacks.report._target_)."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Report on config.hydra.sweep.dir; never raise, the runs' own files are the results."""
        where = "the sweep dir"
        try:
            sweep_dir = Path(str(config.hydra.sweep.dir))
            if not sweep_dir.is_absolute():
                sweep_dir = Path(OmegaConf.select(config, "hydra.runtime.cwd", default=None) or os.getcwd()) / sweep_dir
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

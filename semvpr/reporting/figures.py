"""Sweep-report figures: Recall@N curves, R@1 per aggregator and mask, the seed paper's Figure 3
(attention / masks), top-k retrievals, learned class weights."""

from __future__ import annotations

import math
import textwrap
import zipfile
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text

from semvpr.core.errors import SemvprError
from semvpr.core.io import atomic_file, read_json
from semvpr.reporting.sweep import LEARNED, Job, Sweep, cell_name, mean_std

if TYPE_CHECKING:
    from matplotlib.axes import Axes


# maps.npz: "attention" (the aggregator's own map, if it has one), one array per mask source named
# after it, and these bookkeeping arrays.
ATTENTION = "attention"
MAP_META = ("query_index", "image_paths")
OK_COLOUR, WRONG_COLOUR = "#1a9850", "#d73027"


def _new_figure(width: float, height: float) -> Figure:
    """A pyplot-free Agg figure: no global backend switch, safe inside a user's process."""
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, out: Path) -> None:
    """Save a PNG via a temp name and rename; every text as written (a run's labels are data: a ``$`` in one is
    never TeX)."""
    for text in fig.findobj(Text):
        text.set_parse_math(False)
    with atomic_file(out) as fh:
        fig.savefig(fh, format="png", dpi=100)


@lru_cache(maxsize=256)
def _thumb(path: Path | None, max_side: int = 320) -> np.ndarray | None:
    """A small RGB copy of an image, or None when it cannot be read."""
    if path is None:
        return None
    from PIL import Image

    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            im.thumbnail((max_side, max_side))
            return np.asarray(im)
    except OSError:
        return None


def _na(ax: Axes, what: str = "n/a") -> None:
    """Mark a panel whose input is missing."""
    ax.text(0.5, 0.5, what, ha="center", va="center", fontsize=11, color="0.4", transform=ax.transAxes)
    ax.set_xticks([])
    ax.set_yticks([])


def _show(ax: Axes, img: Any, missing: str) -> None:
    """An image without ticks, or the ``missing`` mark when there is none."""
    if img is None:
        _na(ax, missing)
        return
    ax.imshow(img)
    ax.set_xticks([])
    ax.set_yticks([])


def _curve(recalls: Any) -> dict[int, float]:
    """metrics["recalls"] ({"1": r, "2": r, ...}) as {N: recall}, skipping malformed entries."""
    out: dict[int, float] = {}
    for key, value in (recalls or {}).items() if isinstance(recalls, dict) else ():
        try:
            out[int(key)] = float(value)
        except (TypeError, ValueError):
            continue
    return {n: v for n, v in out.items() if math.isfinite(v)}


def recall_curves(sweep: Sweep, out: Path) -> str | None:
    """Recall@N curves (mean over seeds, ±1 std band) per sweep row, one panel per backbone; else a skip reason."""
    panels = []
    for bb in sweep.backbones:
        lines = []
        for f in sweep.cells:
            curves = [c for c in (_curve(j.metrics.get("recalls")) for j in sweep.jobs_of(f, bb) if j.ok) if c]
            ns = sorted(set.intersection(*(set(c) for c in curves))) if curves else []
            if ns:
                lines.append((f, ns, np.array([[c[n] for n in ns] for c in curves])))
        if lines:
            panels.append((bb, lines))
    if not panels:
        return 'no finished run recorded per-N recalls (metrics.json "recalls")'
    fig = _new_figure(5.5 * len(panels), 4.3)
    for ax, (bb, lines) in zip(fig.subplots(1, len(panels), squeeze=False)[0], panels):
        for f, ns, ys in lines:
            mean = ys.mean(axis=0)
            (line,) = ax.plot(
                ns,
                mean,
                marker="o",
                ms=3,
                ls="--" if sweep.upper_bound(f) else "-",
                color=f"C{sweep.cells.index(f) % 10}",  # same colour per row in every panel
                label=f"{sweep.label(f)} (n={len(ys)})",
            )
            if len(ys) > 1:
                std = ys.std(axis=0, ddof=1)
                ax.fill_between(ns, mean - std, mean + std, color=line.get_color(), alpha=0.15)
        ax.set(
            title=textwrap.fill(f"backbone: {bb}", 28),
            xlabel="N (top-N retrieved)",
            ylabel="Recall@N (%)",
            ylim=(0, 100),
        )
        top = max(max(ns) for _, ns, _ in lines)
        ax.set_xlim(1, top)
        ax.set_xticks([n for n in (1, 5, 10, 15, 20, 25, 50, 100) if n <= top])  # the reported N, not 2.5 steps
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=9)
    fig.suptitle("Recall@N per aggregator · mask (mean over seeds, band = ±1 std)")
    _save(fig, out)
    return None


def matrix_bars(sweep: Sweep, out: Path) -> str | None:
    """Grouped bars of test R@1 (mean ± std over seeds): one group per aggregator, one bar per mask,
    one panel per backbone; else a skip reason."""
    panels = []
    for bb in sweep.backbones:
        bars = {
            (a, m): [j.recall(1) for j in sweep.jobs_of(cell_name(a, m), bb) if j.ok]
            for a in sweep.aggregators
            for m in sweep.masks
        }
        bars = {k: v for k, v in bars.items() if any(math.isfinite(x) for x in v)}
        if bars:
            panels.append((bb, bars))
    if not panels:
        return "no finished run recorded test R@1"
    masks = sweep.masks
    fig = _new_figure(max(6.0, 1.4 * len(sweep.aggregators) * len(panels) + 1.5), 4.3)
    for ax, (bb, bars) in zip(fig.subplots(1, len(panels), squeeze=False)[0], panels):
        aggs = [a for a in sweep.aggregators if any(k[0] == a for k in bars)]
        width = 0.8 / len(masks)
        for i, m in enumerate(masks):
            xs = [x for x, a in enumerate(aggs) if (a, m) in bars]
            if not xs:
                continue
            stats = [mean_std(bars[(aggs[x], m)]) for x in xs]
            ax.bar(
                np.array(xs) + (i - (len(masks) - 1) / 2) * width,
                [mu for mu, _ in stats],
                width,
                yerr=[sd if math.isfinite(sd) else 0.0 for _, sd in stats],
                capsize=2,
                color=f"C{i % 10}",
                label=sweep.mask_label(m),
            )
        ax.set_xticks(range(len(aggs)), aggs)
        ax.set(title=textwrap.fill(f"backbone: {bb}", 28), ylabel="test R@1 (%)", ylim=(0, 100))
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8, title="mask", title_fontsize=8)
    fig.suptitle("R@1 per aggregator and mask (mean over seeds, bar = ±1 std)")
    _save(fig, out)
    return None


def _maps(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays of a maps.npz, or None when it is missing or damaged."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return None


def _map_source(sweep: Sweep, backbone: str, key: str) -> tuple[Job, dict] | None:
    """The first job (rows in reading order, ok runs and low seeds first) whose maps.npz has array `key`."""
    for f in sweep.cells:
        for job in sweep.jobs_of(f, backbone, needs="maps.npz"):
            maps = _maps(job.dir / "maps.npz")
            if maps and key in maps and "query_index" in maps:
                return job, maps
    return None


def _image_of(sources: Any, qi: int) -> str | None:
    """The stored image path of query `qi` from whichever maps.npz lists it."""
    for src in sources:
        if src and "image_paths" in src[1] and qi in list(src[1]["query_index"]):
            return str(src[1]["image_paths"][list(src[1]["query_index"]).index(qi)])
    return None


def figure3(sweep: Sweep, out: Path, max_queries: int = 4) -> str | None:
    """Seed Figure 3: per query a row of image, the aggregator's attention and each mask source's mask
    (whichever the sweep's runs wrote); else a skip reason."""
    keys = sorted(
        {
            k
            for job in sweep.jobs
            if (job.dir / "maps.npz").is_file()
            for k in (_maps(job.dir / "maps.npz") or {})
            if k not in MAP_META
        },
        key=lambda k: (k != ATTENTION, k in sweep.upper_bounds, k),
    )  # upper bounds last
    # the backbone whose runs fill the most columns; sorted order breaks ties
    candidates = [(bb, {key: _map_source(sweep, bb, key) for key in keys}) for bb in sweep.backbones]
    bb, sources = max(candidates, key=lambda c: sum(v is not None for v in c[1].values()))
    if not any(sources.values()):
        return "no job wrote maps.npz with attention or mask arrays"
    cols = [
        (key, "attention\n(per-image scaled)" if key == ATTENTION else f"{key} mask\n(bright = static)", sources[key])
        for key in keys
        if sources[key]
    ]
    first = next(s for s in sources.values() if s)
    queries = [int(q) for q in first[1]["query_index"][:max_queries]]
    fig = _new_figure(2.6 * (1 + len(cols)), 2.2 * len(queries) + 0.8)
    axes = fig.subplots(len(queries), 1 + len(cols), squeeze=False)
    for r, qi in enumerate(queries):
        stored = _image_of(sources.values(), qi)
        img = _thumb(sweep.image_path(stored)) if stored else None
        ax = axes[r, 0]
        _show(ax, img, "image n/a")
        ax.set_ylabel(f"query {qi}\n{Path(stored).name[:28] if stored else ''}", fontsize=8)
        for c, (key, _title, src) in enumerate(cols, start=1):
            ax = axes[r, c]
            idx = list(src[1]["query_index"]).index(qi) if src and qi in list(src[1]["query_index"]) else None
            if idx is None:
                _na(ax)
            else:
                m = src[1][key][idx].astype(np.float32)
                lo, hi = (float(m.min()), float(m.max())) if key == ATTENTION else (0.0, 1.0)
                h, w = img.shape[:2] if img is not None else m.shape
                if img is not None:  # faded image underneath so one sees *what* is kept
                    ax.imshow(img.mean(axis=2), cmap="gray", extent=(0, w, h, 0))
                # feature-grid map stretched over the image extent; nearest keeps binary masks crisp
                ax.imshow(
                    m,
                    cmap="magma",
                    vmin=lo,
                    vmax=max(hi, lo + 1e-6),
                    extent=(0, w, h, 0),
                    alpha=0.7 if img is not None else 1.0,
                    interpolation="bilinear" if key == ATTENTION else "nearest",
                )
                ax.set_xticks([])
                ax.set_yticks([])
            if r == len(queries) - 1:
                ax.set_xlabel(
                    f"from {src[0].cell}, seed {'?' if src[0].seed is None else src[0].seed}"
                    if src
                    else "no run wrote it",
                    fontsize=8,
                )
        if r == 0:
            for c, title in enumerate(["image"] + [t for _, t, _ in cols]):
                axes[0, c].set_title(title, fontsize=10)
    fig.suptitle(f"Figure 3: attention and static masks ({bb})")
    _save(fig, out)
    return None


def _apart(query: dict[str, Any], hit: dict[str, Any]) -> str:
    """How far a retrieval is from its query, for a title: " · 12 m" (UTM), " · 3 frames" (a frame-aligned
    set), or "" where either has no position."""
    try:
        if "frame" in query and "frame" in hit:
            return f" · {abs(int(hit['frame']) - int(query['frame']))} frames"
        a, b = query["utm"], hit["utm"]
        metres = float(np.hypot(float(a[0]) - float(b[0]), float(a[1]) - float(b[1])))
    except (KeyError, TypeError, ValueError, IndexError):
        return ""
    return f" · {metres:.0f} m" if math.isfinite(metres) else ""


def _retrievals(job: Job) -> dict[str, dict]:
    """retrievals.json of a job as {query path: entry}, empty when missing or damaged."""
    try:
        data = read_json(job.dir / "retrievals.json", "job retrievals")
        return {str(q["query"]): q for q in data["queries"] if isinstance(q, dict) and "query" in q}
    except (SemvprError, KeyError, TypeError):
        return {}


def retrievals(sweep: Sweep, out: Path, max_queries: int = 3, k: int = 3) -> str | None:
    """Per query a block: query image and each row's top-k, framed green (correct) / red; else a skip reason."""
    candidates = []
    for bb in sweep.backbones:
        per_row: dict[str, dict[str, dict]] = {}
        for f in sweep.cells:
            for job in sweep.jobs_of(f, bb, needs="retrievals.json"):
                if entries := _retrievals(job):
                    per_row[f] = entries
                    break
        candidates.append((bb, per_row))
    bb, per_row = max(candidates, key=lambda c: len(c[1]))  # the backbone covering most rows
    if not per_row:
        return "no job wrote retrievals.json"
    order = list(dict.fromkeys(q for entries in per_row.values() for q in entries))

    def disagreement(q: str) -> int:  # queries where the runs differ on top-1 say the most
        tops = {bool(e[q]["topk"][0].get("correct")) for e in per_row.values() if q in e and e[q].get("topk")}
        return -len(tops)

    queries = sorted(order, key=disagreement)[:max_queries]
    rows = list(per_row)
    fig = _new_figure(2.0 * (k + 2.2), 1.45 * len(queries) * len(rows) + 0.7)
    # A column of its own for the rows' labels, written across: a label down the side of a row clips.
    grid = fig.add_gridspec(len(queries) * len(rows), k + 2, width_ratios=[1.4, 0.8] + [1.0] * k)
    for b, q in enumerate(queries):
        r0 = b * len(rows)
        ax = fig.add_subplot(grid[r0 : r0 + len(rows), 0])
        _show(ax, _thumb(sweep.image_path(q)), "query n/a")
        ax.set_title(f"query: {Path(q).name[:24]}", fontsize=8)
        for i, f in enumerate(rows):
            entry = per_row[f].get(q, {})
            label = fig.add_subplot(grid[r0 + i, 1])
            label.axis("off")
            label.text(0.5, 0.5, textwrap.fill(sweep.label(f), 14), ha="center", va="center", fontsize=9)
            for c in range(k):
                ax = fig.add_subplot(grid[r0 + i, c + 2])
                hits = entry.get("topk") or []
                if c >= len(hits):
                    _na(ax)
                    continue
                hit = hits[c]
                img = _thumb(sweep.image_path(str(hit.get("path", ""))))
                if img is None:
                    _na(ax, "image n/a")
                else:
                    ax.imshow(img)
                    ax.set_xticks([])
                    ax.set_yticks([])
                colour = OK_COLOUR if hit.get("correct") else WRONG_COLOUR
                for spine in ax.spines.values():
                    spine.set(edgecolor=colour, linewidth=4)
                ax.set_title(f"#{c + 1}" + _apart(entry, hit), fontsize=8)
    fig.suptitle(
        f"Top-{k} retrievals per aggregator · mask ({bb}; green = correct, red = wrong)\n"
        "queries where the runs disagree most on the top-1"
    )
    _save(fig, out)
    return None


def class_weights(sweep: Sweep, out: Path) -> str | None:
    """Learned per-class weights (mean ± std over seeds) per mask source and backbone; else a skip reason."""
    runs = sweep.learned_weights()
    if not runs:
        return "no run learned class weights (mask.weights=learned)"
    cells = list(runs)
    classes = list(runs[cells[0]][0])
    fig = _new_figure(max(8.0, 0.55 * len(classes)), 3.6)
    ax = fig.add_subplot()
    width = 0.8 / len(cells)
    x = np.arange(len(classes))
    for i, cell in enumerate(cells):
        stats = [mean_std([float(w[name]) for w in runs[cell] if name in w]) for name in classes]
        means = [m for m, _ in stats]
        stds = [s if math.isfinite(s) else 0.0 for _, s in stats]
        ax.bar(
            x + (i - (len(cells) - 1) / 2) * width,
            means,
            width,
            yerr=stds,
            capsize=2,
            label=f"{cell[1].removesuffix(LEARNED)} ({cell[0]}, {len(runs[cell])} seeds)",
        )
    ax.set_xticks(x, classes, rotation=45, ha="right", fontsize=8)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("learned weight w_c")
    ax.axvline(9.5, color="0.6", lw=0.8, ls="--")  # static classes (trainIds 0-9) | the rest
    ax.legend(fontsize=8, ncol=min(3, len(cells)))
    ax.set_title("Which classes matter for place recognition: learned class weights (start 0.98 | 0.02)")
    _save(fig, out)
    return None


def mask_figure(
    rows: list[tuple[np.ndarray, str, dict[str, np.ndarray]]], columns: dict[str, str], out: Path, title: str
) -> None:
    """Figure 3 on a segmentation set: per image a row of the image and binary static masks (bright = static)
    over the faded image; a mask's NaN pixels (unlabelled) show the image only."""
    fig = _new_figure(2.6 * (1 + len(columns)), 2.2 * len(rows) + 0.8)
    axes = fig.subplots(len(rows), 1 + len(columns), squeeze=False)
    for r, (img, name, masks) in enumerate(rows):
        h, w = img.shape[:2]
        axes[r, 0].imshow(img)
        axes[r, 0].set_ylabel(name[:28], fontsize=8)
        for c, key in enumerate(columns, start=1):
            ax = axes[r, c]
            if key not in masks:
                _na(ax)
                continue
            ax.imshow(img.mean(axis=2), cmap="gray", extent=(0, w, h, 0))
            ax.imshow(
                masks[key].astype(np.float32),
                cmap="magma",
                vmin=0.0,
                vmax=1.0,
                extent=(0, w, h, 0),
                alpha=0.7,
                interpolation="nearest",
            )
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    for c, heading in enumerate(["image", *columns.values()]):
        axes[0, c].set_title(heading, fontsize=10)
    fig.suptitle(title)
    _save(fig, out)

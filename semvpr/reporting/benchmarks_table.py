"""One checkpoint on several benchmarks: the table of an evaluation multirun (``results.csv`` /
``results.md``), a row per job's ``eval.json`` followed by the published numbers of the same model family
on the same protocol (``semvpr/data/published.yaml``).

A row evaluated with a mask whose sweep also evaluated the same checkpoint on the same set without one
gets ``R@1 vs no mask``: the paired R@1 difference over the queries (each job's ``ranks.npy``) with its
95 % bootstrap interval (``semvpr.reporting.paired``), so a few hundred queries say which gains they
support."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from semvpr.core.errors import SemvprError
from semvpr.core.io import check_replaceable, existing_dir, read_json, read_yaml, regular_file, write_csv, write_text
from semvpr.data.published import results_for
from semvpr.reporting.markdown import md_cell
from semvpr.reporting.paired import paired_gain
from semvpr.reporting.sweep import job_dirs, unstarted_jobs
from semvpr.retrieval.controls import APPLIES, CONTROLS, MaskControl
from semvpr.retrieval.recall import RECALL_NS

COLUMNS = (
    "data",
    "set",
    "benchmark",
    *(f"R@{n}" for n in RECALL_NS),
    "queries",
    "database",
    "descriptor_dim",
    "precision",
    "wall_s",
    "R@1 vs no mask",
    "source",
)
#: Each eval job's per-query first-hit ranks (``semvpr.eval``), in the set's query order.
RANKS_FILE = "ranks.npy"
#: Each eval job's per-query hits at each N and retrieved database indices (``semvpr.eval.query_hits``).
HITS_FILE = "hits.npz"


def _job_dirs(sweep_dir: Path) -> list[Path]:
    """Eval job dirs of the sweep (Hydra's numbered subdirs, or any holding eval.json), in job order."""
    dirs = job_dirs(sweep_dir, "eval")
    dirs.discard(sweep_dir)
    return sorted(dirs, key=lambda d: (len(d.name), d.name))


_QUOTES = "'\""


def _overrides(job_dir: Path, sweep_dir: Path) -> str:
    """A failed job's label: its data= and data.root= overrides, else every override it was given (a sweep
    over checkpoints and masks; a path relative to the sweep dir, as :func:`_source` shows it), else the
    job dir's name; read as plain YAML (``core.io.read_yaml``: nothing resolved, no aliases)."""
    path = job_dir / ".hydra" / "overrides.yaml"
    try:
        items = read_yaml(path, "run record") if path.is_file() else []
    except SemvprError:  # a damaged .hydra dir only costs the label
        return job_dir.name
    given = tuple(o for o in items if isinstance(o, str)) if isinstance(items, list) else ()
    return _label(given, sweep_dir) or job_dir.name


#: What an ok eval.json must hold for its row, and the types each may have.
_RESULT_KEYS: dict[str, tuple[type, ...]] = {
    "data": (str,),
    "set": (str,),
    "model": (str,),
    "aggregator": (str,),
    "mask": (str,),
    "checkpoint": (str,),
    **{f"test/R@{n}": (int, float) for n in RECALL_NS},
    "queries": (int,),
    "database": (int,),
    "descriptor_dim": (int,),
    "wall_s": (int, float),
}


def _malformed(result: dict[str, Any]) -> str | None:
    """Why an ok eval.json cannot make a row (a missing key, a value of the wrong type or out of its range:
    recalls in [0, 100] and not falling with N, counts >= 1, a finite wall time >= 0, a known mask control),
    or None."""
    for key, types in _RESULT_KEYS.items():
        value = result.get(key)
        if not isinstance(value, types) or isinstance(value, bool):
            return f"eval.json has no usable {key!r} ({type(value).__name__})"
    if result.get("benchmark") is not None and not isinstance(result["benchmark"], str):
        return "eval.json has no usable 'benchmark'"
    for key, known in (("mask_control", CONTROLS), ("mask_apply", APPLIES)):
        if key in result and result[key] not in known:
            return f"eval.json's {key}={result[key]!r} is not one of {list(known)}"
    seed = result.get("mask_control_seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        return f"eval.json's mask_control_seed={seed!r} is not a whole number >= 0"
    recalls = [result[f"test/R@{n}"] for n in RECALL_NS]
    for n, value in zip(RECALL_NS, recalls, strict=True):
        if not 0 <= value <= 100:  # NaN fails too
            return f"eval.json's test/R@{n}={value} is not a recall in [0, 100]"
    if any(b < a for a, b in zip(recalls, recalls[1:])):
        return f"eval.json's recalls {recalls} fall as N grows"
    for key in ("queries", "database", "descriptor_dim"):
        if result[key] < 1:
            return f"eval.json's {key}={result[key]} is not a count >= 1"
    if not 0 <= result["wall_s"] < float("inf"):
        return f"eval.json's wall_s={result['wall_s']} is not a finite time >= 0"
    return None


def _source(checkpoint: str, sweep_dir: Path) -> str:
    """A checkpoint path as the table shows it: relative to the sweep dir (a table never carries the
    absolute paths of the machine that made it)."""
    try:
        return os.path.relpath(checkpoint, sweep_dir.resolve()) if os.path.isabs(checkpoint) else checkpoint
    except ValueError:
        return Path(checkpoint).name


def _model_name(result: dict[str, Any]) -> str:
    """The model as a row names it: an author's release by its name, else semvpr's backbone-aggregator."""
    release = result.get("release")
    return release if isinstance(release, str) and release else result["model"]


def _mask_label(result: dict[str, Any]) -> str:
    """The mask as a row names it: the source, the directory its segmenter came from, and its control where it
    is not the source's own mask on every image (``retrieval.controls``; an eval.json without one had none)."""
    label = f"mask={result['mask']}"
    if result.get("mask_checkpoint"):
        label += f" from {result['mask_checkpoint']}"
    control = MaskControl(
        result.get("mask_control", "none"), result.get("mask_apply", "both"), result.get("mask_control_seed", 0)
    )
    return f"{label}, {control.label()}" if control.active else label


def table_rows(sweep_dir: str | Path) -> list[dict[str, Any]]:
    """A row per job (failed or malformed ones say why), each followed by its published rows."""
    sweep_dir = existing_dir(sweep_dir, "sweep dir", "pass the multirun dir of `python -m semvpr.eval -m ...`")
    jobs = _job_dirs(sweep_dir)
    if not jobs:
        raise SemvprError(f"no evaluation jobs in {sweep_dir} (no subdir holds eval.json or .hydra/)")
    rows: list[dict[str, Any]] = []
    measured: list[tuple[dict[str, Any], dict[str, Any], Path]] = []
    for job in jobs:
        try:
            result = read_json(job / "eval.json", "job result")
        except SemvprError as err:  # the job's folder named as the table's rows name it, not by an absolute path
            why = str(err).replace(f"{job / 'eval.json'}", "eval.json").replace(f"{sweep_dir}{os.sep}", "")
            result = {"status": "failed", "error": UNFINISHED if not (job / "eval.json").exists() else why}
        if not isinstance(result, dict):
            result = {"status": "failed", "error": "eval.json is not an object"}
        elif result.get("status") == "ok" and (why := _malformed(result)) is not None:
            result = {"status": "failed", "error": why}
        if result.get("status") != "ok":
            rows.append({"data": _overrides(job, sweep_dir), "source": f"failed: {result.get('error')}"})
            continue
        rows.append(
            {
                "data": result["data"],
                "set": result["set"],
                "benchmark": result.get("benchmark") or "",
                **{f"R@{n}": result[f"test/R@{n}"] for n in RECALL_NS},
                "queries": result["queries"],
                "database": result["database"],
                "descriptor_dim": result["descriptor_dim"],
                "precision": result.get("precision") or "",
                "wall_s": result["wall_s"],
                "source": f"measured: {_model_name(result)} ({result['aggregator']}, {_mask_label(result)}), "
                f"{_source(result['checkpoint'], sweep_dir)}",
            }
        )
        measured.append((rows[-1], result, job))
        for published in results_for(result["model"], result.get("benchmark")):
            rows.append(
                {
                    "data": "published",
                    "set": result["set"],
                    "benchmark": published["benchmark"],
                    **{f"R@{n}": published.get(f"R@{n}", "") for n in RECALL_NS},
                    "source": f"{published['model']}: {published['source']}",
                }
            )
    rows += [{"data": _label(job, sweep_dir), "source": NOT_STARTED} for job in unstarted_jobs(sweep_dir, set(jobs))]
    _mask_gains(measured)
    return rows


#: The ``source`` of a job's row that started and left no eval.json (stopped, killed or still running), and of
#: one the sweep was given that never started.
UNFINISHED = "did not finish: no eval.json"
NOT_STARTED = "not started"


def _label(overrides: tuple[str, ...], sweep_dir: Path) -> str:
    """A job's label from its overrides, as :func:`_overrides` makes it from its record."""
    picked = [o for o in overrides if o.startswith(("data=", "data.root="))] or [
        f"{key}={_source(value.strip(_QUOTES), sweep_dir)}" if sep else key
        for key, sep, value in (o.partition("=") for o in overrides)
    ]
    return " ".join(picked)


def _ranks(job: Path, result: dict[str, Any]) -> np.ndarray | str | None:
    """A job's ``ranks.npy``: a 1-D integer array of one rank per query (-1: no positive) that gives the
    recalls its ``eval.json`` recorded; None where the job has none (an older run), else why it is unusable."""
    path = job / RANKS_FILE
    try:
        if not regular_file(path, "ranks file"):
            return None
        ranks = np.load(path, allow_pickle=False)
    except (SemvprError, OSError, ValueError, EOFError) as err:
        return f"unreadable ranks.npy ({type(err).__name__})"
    if ranks.ndim != 1 or len(ranks) != result["queries"] or not np.issubdtype(ranks.dtype, np.integer):
        return f"ranks.npy is {ranks.dtype}{list(ranks.shape)}, not one rank per query"
    if ranks.size and ranks.min() < -1:
        return "ranks.npy holds ranks below -1"
    for n in RECALL_NS:  # eval.json rounds recalls to 2 decimals
        recall = 100.0 * np.count_nonzero((ranks >= 0) & (ranks < n)) / len(ranks)
        if abs(recall - result[f"test/R@{n}"]) > 0.006:
            return f"ranks.npy gives R@{n} {recall:.2f}, eval.json {result[f'test/R@{n}']}"
    return ranks


def _mask_gains(measured: list[tuple[dict[str, Any], dict[str, Any], Path]]) -> None:
    """Fill ``R@1 vs no mask`` of each masked row whose model (its checkpoint, or with ``ckpt=none`` the
    untrained backbone and aggregator) the sweep also evaluated on the same set without a mask in the same
    precision: the paired gain where both jobs' ranks agree with their recalls, else why not."""

    def pairing(r: dict[str, Any]) -> tuple[Any, ...]:
        return r["set"], r["checkpoint"], r.get("model"), r["queries"], r.get("precision")

    unmasked = {pairing(r): (r, job) for _, r, job in measured if r["mask"] == "none"}
    for row, result, job in measured:
        reference = unmasked.get(pairing(result))
        if result["mask"] == "none" or reference is None:
            continue
        ranks, base = _ranks(job, result), _ranks(reference[1], reference[0])
        if isinstance(ranks, np.ndarray) and isinstance(base, np.ndarray):
            row["R@1 vs no mask"] = paired_gain(ranks == 0, base == 0).text()
        elif isinstance(ranks, str) or isinstance(base, str):
            row["R@1 vs no mask"] = f"none: {ranks if isinstance(ranks, str) else 'the unmasked job: ' + str(base)}"


def write_table(sweep_dir: str | Path) -> Path:
    """Write results.csv and results.md in the sweep dir; returns results.md."""
    rows = table_rows(sweep_dir)
    for name in ("results.csv", "results.md"):  # both targets checked before either is written
        check_replaceable(Path(sweep_dir) / name)
    write_csv(Path(sweep_dir) / "results.csv", COLUMNS, rows)

    def cell(value: Any) -> str:
        return f"{value:.2f}" if isinstance(value, float) else md_cell(value)

    lines = [
        "# Evaluation",
        "",
        (
            "Recall@N in percent over all queries; `published` rows: the same model family on the same "
            "protocol, as cited (semvpr/data/published.yaml). `precision`: the arithmetic the descriptors were "
            "computed in (`32-true`: fp32). `R@1 vs no mask`: the paired R@1 difference "
            "from the same checkpoint on the same set without a mask, in points, with its 95 % bootstrap "
            "interval over the queries."
        ),
        "",
        "| " + " | ".join(COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
    ]
    unfinished = sum(str(row.get("source")).endswith(UNFINISHED) for row in rows)
    unstarted = sum(row.get("source") == NOT_STARTED for row in rows)
    if unfinished or unstarted:
        lines[3:3] = [
            f"**Incomplete:** {unfinished} job(s) did not finish and {unstarted} never started (the sweep was "
            "stopped, or a job's process was killed or has not ended yet); their rows say so.",
            "",
        ]
    lines += ["| " + " | ".join(cell(row.get(c, "")) for c in COLUMNS) + " |" for row in rows]
    md = Path(sweep_dir) / "results.md"
    write_text(md, "\n".join(lines) + "\n")
    return md

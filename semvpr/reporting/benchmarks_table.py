"""One checkpoint on several benchmarks: the table of an evaluation multirun (``results.csv`` /
``results.md``), a row per job's ``eval.json`` followed by the published numbers of the same model family
on the same protocol (``semvpr/data/published.yaml``)."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from semvpr.core.errors import SemvprError
from semvpr.core.io import write_text
from semvpr.data.published import results_for
from semvpr.reporting.markdown import md_cell
from semvpr.retrieval.recall import RECALL_NS

COLUMNS = (
    "data",
    "set",
    "benchmark",
    *(f"R@{n}" for n in RECALL_NS),
    "queries",
    "database",
    "descriptor_dim",
    "wall_s",
    "source",
)


def _job_dirs(sweep_dir: Path) -> list[Path]:
    """Job dirs of the sweep (Hydra's numbered subdirs, or any holding eval.json), in job order."""
    dirs = {p.parent for p in sweep_dir.rglob("eval.json")} | {
        p.parent for p in sweep_dir.rglob(".hydra") if p.is_dir()
    }
    dirs.discard(sweep_dir)
    return sorted(dirs, key=lambda d: (len(d.name), d.name))


def _overrides(job_dir: Path) -> str:
    """A failed job's label: its data= and data.root= overrides (the job dir's name without them)."""
    path = job_dir / ".hydra" / "overrides.yaml"
    try:
        picked = (
            [str(o) for o in OmegaConf.load(path) if str(o).startswith(("data=", "data.root="))]
            if path.is_file()
            else []
        )
        return " ".join(picked) or job_dir.name
    except Exception:  # noqa: BLE001 - a damaged .hydra dir only costs the label
        return job_dir.name


def table_rows(sweep_dir: Path) -> list[dict[str, Any]]:
    """A row per job (failed ones say why), each followed by its published rows."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise SemvprError(
            f"sweep dir {sweep_dir} does not exist; pass the multirun dir of `python -m semvpr.eval -m ...`"
        )
    jobs = _job_dirs(sweep_dir)
    if not jobs:
        raise SemvprError(f"no evaluation jobs in {sweep_dir} (no subdir holds eval.json or .hydra/)")
    rows: list[dict[str, Any]] = []
    for job in jobs:
        try:
            result = json.loads((job / "eval.json").read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            result = {"status": "failed", "error": f"no readable eval.json ({type(err).__name__})"}
        if not isinstance(result, dict) or result.get("status") != "ok":
            error = result.get("error") if isinstance(result, dict) else "eval.json is not an object"
            rows.append({"data": _overrides(job), "source": f"failed: {error}"})
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
                "wall_s": result["wall_s"],
                "source": f"measured: {result['model']} ({result['aggregator']}, mask={result['mask']}"
                f"{' from ' + str(result['mask_checkpoint']) if result.get('mask_checkpoint') else ''}), "
                f"{result['checkpoint']}",
            }
        )
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
    return rows


def write_table(sweep_dir: Path) -> Path:
    """Write results.csv and results.md in the sweep dir; returns results.md."""
    rows = table_rows(sweep_dir)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, restval="", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text(Path(sweep_dir) / "results.csv", buf.getvalue())

    def cell(value: Any) -> str:
        return f"{value:.2f}" if isinstance(value, float) else md_cell(value)

    lines = [
        "# Evaluation",
        "",
        (
            "Recall@N in percent over all queries; `published` rows: the same model family on the same "
            "protocol, as cited (semvpr/data/published.yaml)."
        ),
        "",
        "| " + " | ".join(COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
    ]
    lines += ["| " + " | ".join(cell(row.get(c, "")) for c in COLUMNS) + " |" for row in rows]
    md = Path(sweep_dir) / "results.md"
    write_text(md, "\n".join(lines) + "\n")
    return md

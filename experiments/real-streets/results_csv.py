"""The real-streets tables as a data file: ``results.md`` (written by ``summarize.py``) read back into
``results.csv``, one row per pair, model and mask source.

    python experiments/real-streets/results_csv.py [experiments/real-streets/results.md]

Columns: ``pair``, ``model``, ``mask``, ``seeds``; ``R@1_mean``, ``R@1_std`` (and R@5, R@10; the std is
empty for an untrained baseline's single run); ``gain`` (R@1 over the same model without a mask, paired
by query), ``ci_low``, ``ci_high`` (its 95 % bootstrap interval, empty where ``summarize.py`` printed only
the estimate) and ``excludes_0``. The evaluations it summarises (``run.sh``'s OUT) are not committed.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import write_csv

RECALLS = ("R@1", "R@5", "R@10")
COLUMNS = (
    "pair",
    "model",
    "mask",
    "seeds",
    *(f"{r}_{s}" for r in RECALLS for s in ("mean", "std")),
    "gain",
    "ci_low",
    "ci_high",
    "excludes_0",
)
#: A gain cell: ``−47.3 [−54.0, −40.5] *``, ``−59.2 *`` or ``+2.0 [−1.5, +5.5]``.
GAIN = re.compile(r"(?P<gain>[+−-]?\d+\.\d+)(?: \[(?P<low>[+−-]?\d+\.\d+), (?P<high>[+−-]?\d+\.\d+)\])?(?P<star> \*)?")


def _number(text: str) -> str:
    """A markdown number with the typographic minus as a CSV number."""
    return text.replace("−", "-")


def _recall(cell: str) -> tuple[str, str]:
    """``54.7 ± 1.3`` → (mean, std); ``54.0`` → (mean, '')."""
    mean, _, std = cell.partition(" ± ")
    return _number(mean), std


def rows(report: str) -> list[dict[str, str]]:
    """Every table row of the real-streets results.md, under its pair's heading."""
    out, pair = [], None
    for line in report.splitlines():
        if line.startswith("### "):
            pair = line[4:].partition(" (")[0].strip()
        if not line.startswith("| ") or line.startswith("| model") or pair is None:
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        model, mask, seeds, *recalls, gain = cells
        row = {"pair": pair, "model": model.replace("`", ""), "mask": mask, "seeds": seeds}
        for name, cell in zip(RECALLS, recalls, strict=True):
            row[f"{name}_mean"], row[f"{name}_std"] = _recall(cell)
        m = GAIN.fullmatch(gain)
        if gain and m is None:
            raise SemvprError(f"unreadable gain cell {gain!r}")
        row |= {
            "gain": _number(m["gain"]) if m else "",
            "ci_low": _number(m["low"]) if m and m["low"] else "",
            "ci_high": _number(m["high"]) if m and m["high"] else "",
            "excludes_0": ("yes" if m["star"] else "no") if m else "",
        }
        out.append(row)
    return out


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("report", type=Path, nargs="?", default=Path(__file__).with_name("results.md"))
    args = ap.parse_args()
    table = rows(args.report.read_text(encoding="utf-8"))
    if not table:
        raise SemvprError(f"{args.report}: no table rows (is it summarize.py's results.md?)")
    write_csv(args.report.with_name("results.csv"), COLUMNS, table)
    print(f"{args.report.with_name('results.csv')}: {len(table)} rows")


if __name__ == "__main__":
    main()

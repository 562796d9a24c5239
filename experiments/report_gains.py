"""The paired R@1 gains a sweep report states, as a data file beside it.

    python experiments/report_gains.py experiments/<sweep>/results.md [...]

``semvpr.report`` writes each sweep's means to ``results.csv`` and its paired gains (R@1 of a model
over its baseline, paired by seed) only as sentences of ``results.md``; the job directories they were
computed from are not committed. This reads those sentences back and writes ``gains.csv`` beside each
``results.md``: one row per gain with the section it was stated in, its baseline, the model, the mean and
sample std over seeds, and in how many seeds it was better.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import write_csv

#: One stated gain: ``<model> +6.5 ± 4.4 (better in 3 of 3 seeds)``, models separated by ', '.
GAIN = re.compile(
    r"(?:^|, |: )(?P<model>(?:[^,:()]|\([^)]*\))+?)\s*(?P<mean>[+−-]\d+\.\d+) ± (?P<std>\d+\.\d+) "
    r"\(better in (?P<better>\d+) of (?P<seeds>\d+) seeds\)"
)
COLUMNS = ("section", "baseline", "model", "gain_mean", "gain_std", "seeds_better", "seeds")


def gains(report: str) -> list[dict[str, str]]:
    """Every gain sentence of a ``semvpr.report`` results.md, in order."""
    rows, section = [], "main"
    for line in report.splitlines():
        if line.startswith("## "):
            section = line[3:].strip()
        if "better in" not in line:
            continue
        if line.startswith("- "):  # "- sral: student +1.9 ± 2.6 (...)": gains over the same aggregator's none
            baseline, _, rest = line[2:].partition(": ")
            baseline = f"{baseline} · none"
        else:  # "**R@1 gain over <baseline> (<backbone>)**, ...: <model> +x ± y (...), ..."
            head, _, rest = line.partition("**, ")
            baseline = head.strip("*").removeprefix("R@1 gain ").strip()
            rest = rest.partition(": ")[2]
        for m in GAIN.finditer(rest):
            rows.append(
                {
                    "section": section,
                    "baseline": baseline,
                    "model": m["model"].strip(),
                    "gain_mean": m["mean"].replace("−", "-"),
                    "gain_std": m["std"],
                    "seeds_better": m["better"],
                    "seeds": m["seeds"],
                }
            )
    return rows


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", type=Path, nargs="+", help="results.md files written by semvpr.report")
    args = ap.parse_args()
    for path in args.reports:
        rows = gains(path.read_text(encoding="utf-8"))
        if not rows:
            raise SemvprError(f"{path}: no paired gain in it (is it a semvpr.report results.md?)")
        write_csv(path.with_name("gains.csv"), COLUMNS, rows)
        print(f"{path.with_name('gains.csv')}: {len(rows)} gains")


if __name__ == "__main__":
    main()

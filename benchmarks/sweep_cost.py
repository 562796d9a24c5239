"""Wall time of the default four-way sweep at two revisions of semvpr, measured in one run.

Each revision is checked out (``git worktree``) into a temporary folder and runs
``python -m semvpr.train -m filter=none,attention,unet,mask2former [overrides]`` from an empty cache
of its own (a researcher's first sweep: SynthCity, teacher, pseudo-labels, student and feature
caches all built), one revision after the other in this Python environment. Compare revisions
that generate the same SynthCity (the same ``GENERATOR_VERSION``), or the sweeps do different work.

    python benchmarks/sweep_cost.py --before REV --after REV [--repeats 2] [--override seed=0 ...]

With ``--repeats N`` the sweeps alternate (before, after, before, ...), so a slow spell of a shared
machine does not land on one revision only. Prints each sweep's wall time with its jobs' times
per stage (``timings`` of their ``metrics.json``); last line, totals over the repeats:
``before_s=<t> after_s=<t> ratio=<after/before>``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from semvpr.core.errors import exit_on_user_error

REPO = Path(__file__).resolve().parents[1]
FILTERS = "none,attention,unet,mask2former"


def sweep(rev: str, work: Path, label: str, overrides: list[str]) -> tuple[float, dict[str, dict[str, float]]]:
    """(sweep wall time, job → {stage: seconds, "job": wall_time_s}) of one revision's cold four-way sweep."""
    tree = work / label
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "--quiet", str(tree), rev], check=True)
    try:
        sweep_dir = work / f"{label}-sweep"
        cmd = [
            sys.executable,
            "-m",
            "semvpr.train",
            "-m",
            f"filter={FILTERS}",
            f"paths.cache_dir={work / f'{label}-cache'}",
            f"hydra.sweep.dir={sweep_dir}",
            *overrides,
        ]
        print(f"{label} ({rev}): {' '.join(cmd[1:])}", flush=True)
        env = {**os.environ, "PYTHONPATH": str(tree)}  # this revision's package, not the installed one
        t0 = time.perf_counter()
        subprocess.run(cmd, cwd=tree, env=env, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
    finally:
        subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], check=False)
    return wall, job_timings(sweep_dir)


def job_timings(sweep_dir: Path) -> dict[str, dict[str, float]]:
    """job → {stage: seconds, "job": wall_time_s} from a finished sweep's ``metrics.json`` files."""
    jobs = {}
    for path in sorted(sweep_dir.glob("*/metrics.json")):
        metrics = json.loads(path.read_text())
        if metrics.get("status", "ok") != "ok":
            raise SystemExit(f"{path}: job failed ({metrics.get('error')}); the comparison needs every job")
        jobs[path.parent.name] = {**metrics.get("timings", {}), "job": float(metrics["wall_time_s"])}
    return jobs


def describe(wall: float, jobs: dict[str, dict[str, float]]) -> str:
    """One line: the sweep's wall time, then each job's total and its stages in seconds."""
    parts = [
        f"{name} {t['job']:.0f} s ("
        + ", ".join(f"{k.removesuffix('_s')} {v:.0f}" for k, v in t.items() if k != "job" and v >= 0.5)
        + ")"
        for name, t in jobs.items()
    ]
    return f"sweep {wall:.0f} s; " + "; ".join(parts)


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="git revision of the baseline")
    ap.add_argument("--after", required=True, help="git revision to compare with it")
    ap.add_argument("--repeats", type=int, default=1, help="before/after pairs, run alternately")
    ap.add_argument("--override", action="append", default=[], help="extra Hydra override for both sweeps")
    args = ap.parse_args()
    walls: dict[str, list[float]] = {"before": [], "after": []}
    for i in range(args.repeats):
        for label, rev in (("before", args.before), ("after", args.after)):
            with tempfile.TemporaryDirectory(prefix="semvpr-sweep-cost-") as tmp:
                wall, jobs = sweep(rev, Path(tmp), label, args.override)
            walls[label].append(wall)
            print(f"{label} #{i + 1}: {describe(wall, jobs)}", flush=True)
        print(f"pair #{i + 1}: ratio {walls['after'][-1] / walls['before'][-1]:.3f}", flush=True)
    before, after = sum(walls["before"]), sum(walls["after"])
    print(f"before_s={before:.0f} after_s={after:.0f} ratio={after / before:.3f}")


if __name__ == "__main__":
    main()

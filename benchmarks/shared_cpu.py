"""The default training job alone, then two copies of it at once on the same cores, in one run.

Each copy is ``python -m semvpr.train filter=none`` with the default settings (``threads=auto``) on a warm
cache of its own (built first, untimed), so what is timed is the job a user reruns; the pair starts at the
same moment. A job whose threads fight another's for the cores takes several times as long beside it.

    python benchmarks/shared_cpu.py [--work DIR] [--override KEY=VALUE ...]

Prints each run's wall time; last line: ``alone_s=<t> pair_s=<slower copy's t> ratio=<pair_s / alone_s>``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from semvpr.core.errors import exit_on_user_error

REPO = Path(__file__).resolve().parents[1]


def job(work: Path, name: str, overrides: list[str]) -> subprocess.Popen:
    """Start one default training job with its own run dir, on the shared warm cache."""
    cmd = [
        sys.executable,
        "-m",
        "semvpr.train",
        "filter=none",
        f"paths.cache_dir={work / 'cache'}",
        f"hydra.run.dir={work / name}",
        *overrides,
    ]
    return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def timed(work: Path, names: list[str], overrides: list[str]) -> list[float]:
    """Wall seconds of each job in ``names``, all started at once."""
    t0 = time.perf_counter()
    procs = {name: job(work, name, overrides) for name in names}
    out = []
    for name, proc in procs.items():
        if proc.wait() != 0:
            raise SystemExit(f"{name} failed (exit {proc.returncode}); run it by hand to see why")
        out.append(time.perf_counter() - t0)
    return out


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, help="work folder to keep (default: a temporary one, removed)")
    ap.add_argument("--override", action="append", default=[], help="extra Hydra override of every job")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="semvpr-shared-cpu-") as tmp:
        work = args.work or Path(tmp)
        timed(work, ["warm-up"], args.override)  # builds the cache; not timed
        (alone,) = timed(work, ["alone"], args.override)
        print(f"alone: {alone:.1f} s", flush=True)
        pair = timed(work, ["pair-a", "pair-b"], args.override)
        print(f"two at once: {pair[0]:.1f} s and {pair[1]:.1f} s", flush=True)
    print(f"alone_s={alone:.1f} pair_s={max(pair):.1f} ratio={max(pair) / alone:.2f}")


if __name__ == "__main__":
    main()

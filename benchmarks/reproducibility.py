"""Same seed, same numbers? One job four ways: artifacts built cold, built again cold in another cache,
read warm, and stopped after half the epochs then resumed (``ckpt_path=last``).

The stop is made deterministic: the job runs half the epochs, then its run record
(``.hydra/config.yaml``) is given the full ``trainer.max_epochs``, which is what a run started for the
full count and killed after half of them leaves behind; the resume (``ckpt_path=last`` with the
full count, as the README's resume rule requires the run's own values) continues from its ``last.ckpt``.

    python benchmarks/reproducibility.py [--filters attention unet] [--seed 0] [overrides ...]

Each way runs in a fresh process (as a user would); caches go to a temporary directory. Last line:
``identical=<runs whose test recalls and tested weights equal the first cold run's, of all>
max_r1_diff=<largest |R@1 difference| in points>``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from semvpr.core.errors import exit_on_user_error

REPO = Path(__file__).resolve().parents[1]


def job(run_dir: Path, cache: Path, seed: int, filter_: str, extra: list[str]) -> dict:
    """Run one semvpr.train job in its own process; its metrics.json."""
    cmd = [
        sys.executable,
        "-m",
        "semvpr.train",
        f"filter={filter_}",
        f"seed={seed}",
        f"paths.cache_dir={cache}",
        f"hydra.run.dir={run_dir}",
        *extra,
    ]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return json.loads((run_dir / "metrics.json").read_text())


def record_full_epochs(run_dir: Path, epochs: int) -> None:
    """Make a finished half run look like a run started for ``epochs`` and stopped after half of them:
    its recorded config and overrides say ``trainer.max_epochs=epochs``."""
    record = run_dir / ".hydra" / "config.yaml"
    config = OmegaConf.load(record)
    config.trainer.max_epochs = epochs
    OmegaConf.save(config, record)
    overrides = run_dir / ".hydra" / "overrides.yaml"
    items = [o for o in OmegaConf.to_container(OmegaConf.load(overrides)) if not o.startswith("trainer.max_epochs=")]
    OmegaConf.save(OmegaConf.create([*items, f"trainer.max_epochs={epochs}"]), overrides)


def same_weights(a: dict, b: dict) -> bool:
    """Whether two runs' tested checkpoints hold bit-identical weights."""
    wa, wb = (torch.load(m["checkpoint"], weights_only=True)["state_dict"] for m in (a, b))
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--filters", nargs="+", default=["attention", "unet"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--epochs", type=int, default=4, help="trainer.max_epochs (the stop is after half)")
    ap.add_argument("overrides", nargs="*", help="extra hydra overrides for every job")
    args = ap.parse_args()
    identical, total, max_diff = 0, 0, 0.0
    with tempfile.TemporaryDirectory(prefix="semvpr-repro-") as tmp:
        tmp = Path(tmp)
        for filter_ in args.filters:
            extra = [f"trainer.max_epochs={args.epochs}", *args.overrides]
            start = time.time()
            runs = {
                "cold": job(tmp / filter_ / "cold", tmp / "cache-a", args.seed, filter_, extra),
                "cold, other cache": job(
                    tmp / filter_ / "cold2", tmp / f"cache-b-{filter_}", args.seed, filter_, extra
                ),
                "warm": job(tmp / filter_ / "warm", tmp / "cache-a", args.seed, filter_, extra),
            }
            half = [f"trainer.max_epochs={args.epochs // 2}", *args.overrides]
            job(tmp / filter_ / "resumed", tmp / "cache-a", args.seed, filter_, half)
            record_full_epochs(tmp / filter_ / "resumed", args.epochs)
            runs["stopped + resumed"] = job(
                tmp / filter_ / "resumed", tmp / "cache-a", args.seed, filter_, [*extra, "ckpt_path=last"]
            )
            reference = runs["cold"]
            print(f"filter={filter_} seed={args.seed} ({time.time() - start:.0f} s)")
            for name, m in runs.items():
                same = m["recalls"] == reference["recalls"] and same_weights(m, reference)
                diff = abs(m["test/R@1"] - reference["test/R@1"])
                print(
                    f"  {name:>18}: R@1 {m['test/R@1']:.2f} R@5 {m['test/R@5']:.2f}  "
                    f"{'identical to cold' if same else f'differs (R@1 {diff:+.2f})'}"
                )
                if name != "cold":
                    identical, total, max_diff = identical + same, total + 1, max(max_diff, diff)
    print(f"identical={identical}/{total} max_r1_diff={max_diff:.2f}")


if __name__ == "__main__":
    main()

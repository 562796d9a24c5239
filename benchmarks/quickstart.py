"""The README's cold quick start against one frozen-trunk pass over the same dataset, in one run.

Runs ``python -m semvpr.train -m filter=none,attention,unet,mask2former [overrides]`` from an empty
cache of its own (SynthCity, teacher, pseudo-labels, student, trunk and mask caches all built), then
times one pass of the default frozen trunk over every image of the dataset it generated (train,
val and test; database and queries) at the run's image size and precision, images read from disk
as the sweep reads them.

    python benchmarks/quickstart.py [--install] [--keep DIR] [--fp32] [--override seed=0,1,2 ...]

``--install`` first times the README's install from a fresh clone of this repository's committed HEAD
(``git clone``, ``python3 -m venv``, ``pip install -e '.[dev]'``: the packages come from the index, or
pip's cache where it has them) and runs the sweep with that clone's Python, as a newcomer would.

Prints each job's time per stage (``timings`` of its ``metrics.json``), the stages summed over the
sweep (generation, trunk and mask caching, teacher, pseudo-labels, student, training, ...; a job waiting
on a cache lock counts the wait in the stage it waits for), and the CPU time of the sweep's processes
(user + system, its jobs' workers included): divided by the cores the sweep may use, that is the least wall
time any schedule of the same work could take on them (``floor_s``); what lies between it and ``sweep_s``
is all that running the stages in another order or with other threads could still win, the rest needs
less work. Last line: ``sweep_s=<t> trunk_pass_s=<t> ratio=<sweep/trunk> cpu_s=<t> user_s=<t> sys_s=<t>
sys_share=<sys/cpu> cores=<n> floor_s=<cpu/cores>`` (``sys_s``: kernel time), then ``install_s=<t>
total_s=<install + sweep>`` with ``--install``.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sweep_cost import FILTERS, REPO, describe, job_timings  # noqa: E402

from semvpr.core.errors import exit_on_user_error  # noqa: E402
from semvpr.core.threads import usable_cores  # noqa: E402


def fresh_install(work: Path) -> tuple[float, Path]:
    """(seconds, the clone's Python) of the README's install in a fresh clone of HEAD under ``work``."""
    clone = work / "clone"
    t0 = time.perf_counter()
    subprocess.run(["git", "clone", "--quiet", "--no-local", str(REPO), str(clone)], check=True)
    subprocess.run(["python3", "-m", "venv", str(clone / ".venv")], check=True)
    python = clone / ".venv" / "bin" / "python"
    subprocess.run([str(python), "-m", "pip", "install", "--quiet", "-e", ".[dev]"], cwd=clone, check=True)
    return time.perf_counter() - t0, python


def cold_sweep(
    work: Path, overrides: list[str], python: Path | None = None, cwd: Path = REPO
) -> tuple[float, tuple[float, float]]:
    """(wall time, (user, system) CPU seconds of its processes) of the four-way sweep from an empty cache under ``work``
    (``python`` in ``cwd``: a clone's)."""
    cmd = [
        str(python or sys.executable),
        "-m",
        "semvpr.train",
        "-m",
        f"filter={FILTERS}",
        f"paths.cache_dir={work / 'cache'}",
        f"hydra.sweep.dir={work / 'sweep'}",
        *overrides,
    ]
    print(" ".join(cmd[1:]), flush=True)
    before = cpu_of_children()
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, check=True, stdout=subprocess.DEVNULL)
    after = cpu_of_children()
    return time.perf_counter() - t0, (after[0] - before[0], after[1] - before[1])


def cpu_of_children() -> tuple[float, float]:
    """(user, system) CPU seconds of this process's finished children and all they waited for (a sweep's
    launcher workers and data-loader workers included)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime, usage.ru_stime


@torch.no_grad()
def trunk_pass(work: Path, overrides: list[str], fp32: bool) -> tuple[float, int]:
    """(seconds, images) of one frozen-trunk pass over every image of the sweep's dataset, in bf16 where
    the CPU runs it natively (as the feature caches are written) unless ``fp32``."""
    from hydra import compose, initialize_config_dir

    from semvpr.config.build import build_backbone, build_places
    from semvpr.config.plan import data_settings
    from semvpr.core.precision import autocast
    from semvpr.data.images import ImageDataset

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        # Only the plain overrides (a sweep's comma lists pick their first value).
        plain = [o.split(",")[0] for o in overrides if "=" in o and not o.startswith(("hydra", "+hydra"))]
        cfg = compose(config_name="train", overrides=[f"paths.cache_dir={work / 'cache'}", *plain])
    places = build_places(data_settings(cfg))
    paths = [p for s in places.values() for p in (*s.db_paths, *s.q_paths)]
    backbone = build_backbone(cfg.backbone, cfg.seed).eval()
    loader = DataLoader(
        ImageDataset(paths, tuple(cfg.data.image_size)),
        batch_size=int(cfg.model.eval_batch_size),
        num_workers=int(cfg.data.num_workers),
    )
    t0 = time.perf_counter()
    with autocast("cpu", enabled=not fp32):
        for images, _ in loader:
            backbone.forward_frozen(images.contiguous(memory_format=torch.channels_last), keep_scales=False)
    return time.perf_counter() - t0, len(paths)


#: Stages of a job (metrics.json ``timings``) in pipeline order, with the names the breakdown prints.
STAGES = {
    "data_s": "generation",
    "features_s": "trunk + mask caching",
    "teacher_s": "teacher",
    "labels_s": "pseudo-labels",
    "student_s": "student",
    "init_s": "aggregator init",
    "untrained_eval_s": "untrained eval",
    "fit_s": "training",
    "test_s": "test",
}


def stage_breakdown(sweep_s: float, jobs: dict[str, dict[str, float]]) -> str:
    """One line: each stage's seconds summed over the sweep's jobs (a cold stage is paid by the first job
    that needs it, later ones read the cache), and what the jobs do not account for (start-up, report)."""
    totals = {name: sum(t.get(key, 0.0) for t in jobs.values()) for key, name in STAGES.items()}
    other = sweep_s - sum(t["job"] for t in jobs.values())
    return "stages: " + ", ".join(f"{name} {v:.0f} s" for name, v in totals.items()) + f", outside jobs {other:.0f} s"


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--override", action="append", default=[], help="extra Hydra override of the sweep")
    ap.add_argument("--keep", type=Path, help="work folder to keep (default: a temporary one, removed)")
    ap.add_argument(
        "--fp32", action="store_true", help="time the trunk pass in fp32 (default: as the caches, bf16 where native)"
    )
    ap.add_argument("--install", action="store_true", help="time the install from a fresh clone first")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="semvpr-quickstart-") as tmp:
        work = args.keep or Path(tmp)
        install_s, python, cwd = None, None, REPO
        if args.install:
            install_s, python = fresh_install(work)
            cwd = python.parents[2]
            print(f"install from a fresh clone: {install_s:.0f} s", flush=True)
        sweep_s, (user_s, sys_s) = cold_sweep(work, args.override, python, cwd)
        cpu_s = user_s + sys_s
        jobs = job_timings(work / "sweep")
        print(describe(sweep_s, jobs), flush=True)
        print(stage_breakdown(sweep_s, jobs), flush=True)
        trunk_s, n = trunk_pass(work, args.override, args.fp32)
        print(f"trunk pass: {n} images in {trunk_s:.1f} s", flush=True)
    cores = usable_cores()
    line = (
        f"sweep_s={sweep_s:.0f} trunk_pass_s={trunk_s:.1f} ratio={sweep_s / trunk_s:.1f} "
        f"cpu_s={cpu_s:.0f} user_s={user_s:.0f} sys_s={sys_s:.0f} sys_share={sys_s / cpu_s:.2f} "
        f"cores={cores} floor_s={cpu_s / cores:.0f}"
    )
    if install_s is not None:
        line += f" install_s={install_s:.0f} total_s={install_s + sweep_s:.0f}"
    print(line)


if __name__ == "__main__":
    main()

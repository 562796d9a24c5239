"""Anonymous memory of ``semvpr.eval`` as the evaluated set grows, per ``features.storage`` setting (the frozen
trunk's maps must stay out of RAM beyond ``features.ram_gb``; ARCHITECTURE §5).

Writes N placeholder JPEGs (480x640 by default) in the @UTM@ layout, 80 % database and 20 % queries, and runs
``python -m semvpr.eval data=folder`` on them with an untrained checkpoint of the default model (EfficientNet-Lite0
stage4 + NetVLAD, ``filter=none``), in a fresh process and a fresh cache per (setting, N): the trunk pass, the
masks and the descriptors all run. Each process reads its own anonymous resident memory (``RssAnon`` of
``/proc/self/status``): file-backed pages (a memory-mapped cache, the page cache) are left out, as the kernel can
drop them; decoding workers are processes of their own. Two numbers per process:

- ``peak``: the most a thread sampling every 5 ms saw. The trunk pass's activations rise and fall with every
  batch, and a sampler catches the top of that wave only now and then (the more batches, the likelier): on a
  loaded CPU it moves by up to ~200 MiB between runs of the same set, so its growth per image is noise unless
  the two sizes are thousands of images apart;
- ``held``: read as each side's description returns (``Retriever.describe_store``; localize's queries:
  ``describe_images``), after ``malloc_trim`` hands freed heap back: what evaluation still holds (a trunk copied
  into RAM, gathered descriptors) on top of the model, with no activation in flight.

Settings:

- ``auto``: the default (``features.storage=auto``; the set fits ``ram_gb``);
- ``budget``: ``features.ram_gb`` below the set's trunk maps;
- ``stream``: ``features.storage=stream`` (no trunk cache: images through the frozen trunk);
- ``localize``: ``python -m semvpr.localize`` under the budget, the set's query folder as its queries (the
  database's descriptors as eval computes them, the queries' through the whole model).

The batch (``--batch``) is one that both sides of the smaller set fill: a side smaller than a batch makes the
batch-sized part of the peak (decoded images, activations) smaller there, which would read as growth with the set.

    python benchmarks/eval_memory.py [--sizes 60 420] [--image-size 480 640] [--budget-gb 0.01] [--threads 1]

Per setting one line: peak and held anonymous MiB at both sizes, their growth per extra image (MB) and the wall
times; the last line ``<setting>=<held growth>/<peak growth> ...`` per setting (MB per extra image) and
``growth_mb=<the budget setting's held growth>`` (target: <= 0.1; a descriptor is ~0.014 MB, a trunk map 0.27 MB at
480x640).
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

import torch

from semvpr.config.build import build_backbone, build_mask_source, build_retriever
from semvpr.config.plan import mask_plan, settings_of
from semvpr.core.errors import exit_on_user_error

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale import compose, write_images  # noqa: E402 - the sibling benchmark's data and config helpers

REPO = Path(__file__).resolve().parents[1]
#: MB (10^6 bytes, as the targets are stated) per MiB.
MB_PER_MIB = 2**20 / 1e6

#: Run in the evaluated process (argv: the module, then its overrides): a thread samples RssAnon for the peak, a
#: wrapper reads it as each description returns, and both go to PEAK_FILE as JSON at exit.
CHILD = """
import atexit, ctypes, json, os, runpy, sys, threading, time

from semvpr.retrieval.retriever import Retriever


def anon_kib():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("RssAnon:"):
                return int(line.split()[1])
    return 0


peak, held = [anon_kib()], [0]
libc = ctypes.CDLL("libc.so.6")


def sample():
    while True:
        peak[0] = max(peak[0], anon_kib())
        time.sleep(0.005)


def probed(describe):
    def run(*args, **kwargs):
        out = describe(*args, **kwargs)
        libc.malloc_trim(0)
        held[0] = max(held[0], anon_kib())
        return out

    return run


def report():
    with open(os.environ["PEAK_FILE"], "w") as f:
        json.dump({"peak_kib": max(peak[0], anon_kib()), "held_kib": held[0]}, f)


Retriever.describe_store = probed(Retriever.describe_store)
Retriever.describe_images = probed(Retriever.describe_images)
threading.Thread(target=sample, daemon=True).start()
atexit.register(report)
module = sys.argv[1]
sys.argv = [module, *sys.argv[2:]]
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""

SETTINGS = ("auto", "budget", "stream", "localize")


def write_checkpoint(path: Path) -> None:
    """An untrained checkpoint of the default model (``filter=none``) in the format a run writes."""
    cfg = compose("backbone.weights=none")
    backbone = build_backbone(cfg.backbone, cfg.seed)
    retriever = build_retriever(settings_of(cfg), backbone, build_mask_source(mask_plan(cfg), backbone))
    torch.save({"state_dict": retriever.state_dict(), "hyper_parameters": dict(retriever.hparams)}, path)


def setting_command(setting: str, data: Path, budget_gb: float) -> list[str]:
    """The module a setting runs and its ``features`` (and queries) overrides."""
    return {
        "auto": ["semvpr.eval"],
        "budget": ["semvpr.eval", f"features.ram_gb={budget_gb}"],
        "stream": ["semvpr.eval", "features.storage=stream"],
        "localize": ["semvpr.localize", f"features.ram_gb={budget_gb}", f"queries={data / 'images/test/queries'}"],
    }[setting]


def run_one(ckpt: Path, data: Path, work: Path, hw: tuple[int, int], args: argparse.Namespace, command: list[str]):
    """(wall s, {"peak": MiB, "held": MiB} of anonymous memory, its last stdout line as JSON) of one evaluating
    process."""
    work.mkdir(parents=True, exist_ok=True)
    module, *extra = command
    cmd = [
        sys.executable,
        "-c",
        CHILD,
        module,
        f"ckpt={ckpt}",
        "data=folder",
        f"data.root={data}",
        f"data.image_size=[{hw[0]},{hw[1]}]",
        f"data.num_workers={args.workers}",
        f"model.eval_batch_size={args.batch}",
        f"threads={args.threads}",
        f"paths.cache_dir={work / 'cache'}",
        f"hydra.run.dir={work / 'run'}",
        *extra,
    ]
    env = {**os.environ, "PEAK_FILE": str(work / "peak_kib"), "PYTHONPATH": str(REPO)}
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"{module} failed:\n{proc.stderr[-2000:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    kib = json.loads((work / "peak_kib").read_text())
    return wall, {"peak": kib["peak_kib"] / 1024, "held": kib["held_kib"] / 1024}, result


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs=2, default=(60, 420), help="images per set (80 %% database)")
    ap.add_argument("--image-size", type=int, nargs=2, default=(480, 640))
    ap.add_argument("--budget-gb", type=float, default=0.01, help="features.ram_gb of the budget setting")
    ap.add_argument("--settings", nargs="+", choices=SETTINGS, default=list(SETTINGS))
    ap.add_argument(
        "--batch", type=int, default=12, help="model.eval_batch_size (both sides of the smaller set fill one batch)"
    )
    ap.add_argument("--workers", type=int, default=2, help="decoding workers")
    ap.add_argument("--threads", default="1", help="threads of each evaluation (a number or auto)")
    args = ap.parse_args()
    hw = tuple(args.image_size)
    small, large = sorted(args.sizes)
    if small - int(0.8 * small) < args.batch:
        # A side smaller than a batch makes the peak's batch-sized part (decoded images, activations) smaller at
        # the smaller size, which would read as growth with the set.
        raise SystemExit(f"--batch {args.batch}: the {small - int(0.8 * small)} queries of N={small} must fill a batch")
    growth: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="semvpr-eval-memory-") as tmp:
        tmp = Path(tmp)
        write_checkpoint(tmp / "model.ckpt")
        for n in (small, large):
            write_images(tmp / f"data{n}", n, hw)
        for setting in args.settings:
            runs = {}
            for n in (small, large):
                work = tmp / f"{setting}{n}"
                command = setting_command(setting, tmp / f"data{n}", args.budget_gb)
                runs[n] = run_one(tmp / "model.ckpt", tmp / f"data{n}", work, hw, args, command)
            for n, (_, _, result) in runs.items():
                seen = result.get("database", result.get("queries"))  # eval's database, localize's queries
                if seen not in (int(0.8 * n), n - int(0.8 * n)):
                    raise SystemExit(f"{setting}: the run at N={n} did not see its set ({result})")
            (wall_s, anon_s, _), (wall_l, anon_l, _) = runs[small], runs[large]
            growth[setting] = {k: (anon_l[k] - anon_s[k]) * MB_PER_MIB / (large - small) for k in ("held", "peak")}
            print(
                f"{setting}: held anon {anon_s['held']:.0f} -> {anon_l['held']:.0f} MiB "
                f"({growth[setting]['held']:.3f} MB per extra image), peak anon {anon_s['peak']:.0f} -> "
                f"{anon_l['peak']:.0f} MiB ({growth[setting]['peak']:.3f} MB per extra image) at N={small} -> {large}; "
                f"wall {wall_s:.1f} -> {wall_l:.1f} s"
            )
    line = " ".join(f"{s}={g['held']:.3f}/{g['peak']:.3f}" for s, g in growth.items())
    if "budget" in growth:
        line += f" growth_mb={growth['budget']['held']:.3f}"
    print(line)


if __name__ == "__main__":
    main()

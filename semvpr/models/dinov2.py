"""DINOv2 ViT-B/14 (Oquab et al., 2023) as a semvpr trunk, in the layout of the weights its authors release.

The network is facebookresearch/dinov2's ``dinov2_vitb14`` (``vision_transformer.vit_base`` as
``hub/backbones.py`` builds it): 14 × 14 patches embedded by a strided convolution, a class token, learned
position embeddings for a 37 × 37 grid (518 × 518 images) and the class token, 12 pre-norm blocks of
12-head attention and a GELU MLP of width 4 × 768, each residual branch scaled by a LayerScale, LayerNorms
with eps 1e-6, no register tokens. Other grids take the position embeddings as DINOv2's
``interpolate_pos_encoding`` makes them: the 37 × 37 grid resized bicubically, without antialiasing, by the
scale factors (h + 0.1) / 37 and (w + 0.1) / 37 (its ``interpolate_offset``), and left as they are for a
square image of a 37 × 37 grid. Image sides must be multiples of 14 (DINOv2's ``PatchEmbed`` asserts it).

Units: ``embed``, ``block0`` … ``block11``, ``norm``. Between units the tokens travel as one map
(B, 768, h + 1, w): row 0 holds the class token in column 0 (zeros beside it) and rows 1 … h the patch
tokens on their grid, so that the frozen prefix's output is cached, chunked and moved as any trunk's is.
``norm`` gives the local features as SALAD's and BoQ's DINOv2 wrappers do: the patch tokens after the final
LayerNorm (``final_norm``; BoQ's wrapper leaves it out, its weights unused) reshaped to (B, 768, h, w); with
``class_token`` the class token (normalised likewise) follows as 768 more channels, the same at every
location, for an aggregator whose global token it is (``SALAD(global_token="class")``). ``norm`` has no
weights the cache depends on and costs one LayerNorm, so it always runs after the cache: with
``train_from=None`` the cache holds the last block's tokens and ``norm`` stays frozen.

Weights: ``none`` (random, DINOv2's initialisation) or a file in DINOv2's naming (``dinov2_vitb14_pretrain.pth``:
``cls_token``, ``pos_embed``, ``mask_token``, ``patch_embed.proj``, ``blocks.N.*``, ``norm``), or a SALAD or
BoQ release file, whose trunk is read off its layout (``models.released``). Never downloaded.
SALAD fine-tunes the last 4 blocks (``train_from=block8``), BoQ the last 2 (``train_from=block10``).
A student decodes image-aligned feature maps, not these token maps: the masks of this trunk come from the
teacher (or the oracle).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.errors import SemvprError
from semvpr.models.backbones import Backbone, trunk_state

PATCH = 14
WIDTH = 768
DEPTH = 12
HEADS = 12
#: The position embeddings' grid side (518 / 14) and DINOv2's interpolation offset.
POS_GRID = 37
INTERPOLATE_OFFSET = 0.1
LN_EPS = 1e-6
DINOV2_UNITS: tuple[tuple[str, int, int, bool], ...] = (
    ("embed", WIDTH, PATCH, True),
    *((f"block{i}", WIDTH, PATCH, True) for i in range(DEPTH)),
    ("norm", WIDTH, PATCH, True),
)
#: DINOv2's key prefixes → this backbone's (one entry per prefix; a key takes its longest match).
DINOV2_KEYS: tuple[tuple[str, str], ...] = (
    ("cls_token", "units.0.cls_token"),
    ("pos_embed", "units.0.pos_embed"),
    ("mask_token", "units.0.mask_token"),
    ("patch_embed.", "units.0.patch_embed."),
    *((f"blocks.{i}.", f"units.{i + 1}.") for i in range(DEPTH)),
    ("norm.", f"units.{DEPTH + 1}.norm."),
)


def tokens_of(x: Tensor) -> Tensor:
    """(B, C, h + 1, w) token map → (B, 1 + h·w, C) tokens, the class token first."""
    return torch.cat([x[:, :, 0, :1], x[:, :, 1:].flatten(2)], dim=2).transpose(1, 2)


def token_map(tokens: Tensor, w: int) -> Tensor:
    """(B, 1 + h·w, C) tokens → (B, C, h + 1, w) token map (row 0: the class token, then zeros)."""
    b, n, c = tokens.shape
    t = tokens.transpose(1, 2)
    first = F.pad(t[:, :, :1], (0, w - 1))
    return torch.cat([first, t[:, :, 1:]], dim=2).reshape(b, c, (n - 1) // w + 1, w)


class PatchEmbed(nn.Module):
    """DINOv2's ``PatchEmbed``: a 14 × 14 convolution of stride 14 (``proj``)."""

    def __init__(self) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, WIDTH, kernel_size=PATCH, stride=PATCH)


class Embedding(nn.Module):
    """Patch embedding, class token and (interpolated) position embeddings → the token map."""

    def __init__(self) -> None:
        super().__init__()
        self.patch_embed = PatchEmbed()
        self.cls_token = nn.Parameter(torch.zeros(1, 1, WIDTH))
        self.pos_embed = nn.Parameter(torch.zeros(1, POS_GRID * POS_GRID + 1, WIDTH))
        # DINOv2's masked-image-modelling token: in its files, never used to describe an image.
        self.register_buffer("mask_token", torch.zeros(1, WIDTH))

    def positions(self, h: int, w: int, square: bool) -> Tensor:
        """(1, 1 + h·w, C) position embeddings for an h × w grid (DINOv2's ``interpolate_pos_encoding``)."""
        n = self.pos_embed.shape[1] - 1
        if h * w == n and square:
            return self.pos_embed
        side = math.isqrt(n)
        pos = self.pos_embed.float()
        grid = pos[:, 1:].reshape(1, side, side, -1).permute(0, 3, 1, 2)
        scale = ((h + INTERPOLATE_OFFSET) / side, (w + INTERPOLATE_OFFSET) / side)
        grid = F.interpolate(grid, scale_factor=scale, mode="bicubic", antialias=False)
        return torch.cat([pos[:, :1], grid.permute(0, 2, 3, 1).reshape(1, h * w, -1)], dim=1)

    def forward(self, x: Tensor) -> Tensor:
        """(B, 3, H, W) normalised images → (B, C, h + 1, w) token map."""
        height, width = x.shape[-2:]
        if height % PATCH or width % PATCH:
            raise SemvprError(
                f"DINOv2 ViT-B/14 needs image sides that are multiples of {PATCH}, got {height} x {width}: "
                "set data.image_size (e.g. [322, 322])"
            )
        patches = self.patch_embed.proj(x)
        h, w = patches.shape[-2:]
        tokens = torch.cat([self.cls_token.expand(len(x), -1, -1), patches.flatten(2).transpose(1, 2)], dim=1)
        tokens = tokens + self.positions(h, w, height == width).to(tokens.dtype)
        return token_map(tokens, w)


class Attention(nn.Module):
    """Multi-head self-attention with one ``qkv`` projection (rows q, k, v; heads within each)."""

    def __init__(self) -> None:
        super().__init__()
        self.qkv = nn.Linear(WIDTH, 3 * WIDTH)
        self.proj = nn.Linear(WIDTH, WIDTH)

    def forward(self, x: Tensor) -> Tensor:
        b, n, c = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, HEADS, c // HEADS).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class LayerScale(nn.Module):
    """A learned per-channel scale ``gamma`` of a residual branch."""

    def __init__(self) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(WIDTH))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    """``fc1``, GELU, ``fc2``."""

    def __init__(self) -> None:
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(WIDTH, 4 * WIDTH), nn.Linear(4 * WIDTH, WIDTH)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class Block(nn.Module):
    """x + ls1(attn(norm1(x))), then + ls2(mlp(norm2(x))), on the token map."""

    def __init__(self) -> None:
        super().__init__()
        self.norm1, self.norm2 = nn.LayerNorm(WIDTH, eps=LN_EPS), nn.LayerNorm(WIDTH, eps=LN_EPS)
        self.attn, self.mlp = Attention(), Mlp()
        self.ls1, self.ls2 = LayerScale(), LayerScale()

    def forward(self, x: Tensor) -> Tensor:
        tokens = tokens_of(x)
        tokens = tokens + self.ls1(self.attn(self.norm1(tokens)))
        tokens = tokens + self.ls2(self.mlp(self.norm2(tokens)))
        return token_map(tokens, x.shape[-1])


class Head(nn.Module):
    """The final LayerNorm (``final_norm``) and the patch tokens as a (B, C, h, w) map, the class token
    after them where asked (see the module docstring)."""

    def __init__(self, final_norm: bool, class_token: bool) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(WIDTH, eps=LN_EPS)
        self.final_norm, self.class_token = final_norm, class_token
        if not final_norm:
            self.norm.requires_grad_(False)  # in the file, unused

    def forward(self, x: Tensor) -> Tensor:
        tokens = tokens_of(x)
        if self.final_norm:
            tokens = self.norm(tokens)
        b, _, c = tokens.shape
        h, w = x.shape[-2] - 1, x.shape[-1]
        patches = tokens[:, 1:].transpose(1, 2).reshape(b, c, h, w)
        if not self.class_token:
            return patches
        return torch.cat([patches, tokens[:, 0, :, None, None].expand(b, c, h, w)], dim=1)


def _init_weights(module: nn.Module) -> None:
    """DINOv2's initialisation (``init_weights_vit_timm``, LayerScale at the hub's 1.0)."""
    if isinstance(module, nn.Linear):
        nn.init.trunc_normal_(module.weight, std=0.02)
        nn.init.zeros_(module.bias)
    elif isinstance(module, Embedding):
        nn.init.trunc_normal_(module.pos_embed, std=0.02)
        nn.init.normal_(module.cls_token, std=1e-6)


def dinov2_state(weights: str | Path) -> dict[str, Tensor] | None:
    """The trunk's weights in DINOv2's naming for ``weights`` ("none" | a file in DINOv2's naming or a SALAD /
    BoQ release), None for "none"."""
    if str(weights) == "none":
        return None
    path = Path(weights)
    if not path.is_file():
        raise SemvprError(
            f"backbone weights file {path} does not exist; pass DINOv2's dinov2_vitb14_pretrain.pth (or a SALAD / "
            "BoQ release file), or backbone.weights=none (there are no ImageNet weights for this trunk)"
        )
    return trunk_state(path, "dinov2_vitb14")


class DINOv2Backbone(Backbone):
    """DINOv2 ViT-B/14: 768 channels at stride 14 (the module docstring says how its tokens travel)."""

    image_maps = False

    def __init__(
        self,
        weights: str | Path = "none",
        train_from: str | None = None,
        final_norm: bool = True,
        class_token: bool = False,
    ) -> None:
        embed, blocks, head = Embedding(), [Block() for _ in range(DEPTH)], Head(final_norm, class_token)
        units = [("embed", embed), *((f"block{i}", b) for i, b in enumerate(blocks)), ("norm", head)]
        for _, module in units:
            module.apply(_init_weights)
        # The MLP widens each token four times: the widest activation per pixel of a unit.
        super().__init__(units, DINOV2_UNITS, train_from or "norm", expansion=4.0)
        self.train_from = train_from
        if train_from is None:
            head.requires_grad_(False)
        #: The class token follows the patch channels of the local features (twice ``out_channels`` in all).
        self.class_token = class_token
        state = dinov2_state(weights)
        if state is not None:
            self._load(state, weights)

    def _load(self, state: dict[str, Tensor], source: str | Path) -> None:
        """All of the trunk's weights from ``state`` (DINOv2's naming), checked by name and shape; a wrong key
        is one line in DINOv2's naming."""
        from semvpr.models.released import rename

        own, ours = self.state_dict(), {}
        for key, value in state.items():
            target = rename(str(key), DINOV2_KEYS)
            shape = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
            if target not in own or shape != tuple(own[target].shape):
                needs = f"needs {tuple(own[target].shape)}" if target in own else "no such weight"
                raise SemvprError(
                    f"backbone weights {source}: {key!r} ({shape}) does not fit DINOv2 ViT-B/14 ({needs})"
                )
            ours[target] = value
        missing = sorted(set(own) - set(ours))
        if missing:
            name = rename(missing[0], tuple((b, a) for a, b in DINOV2_KEYS))
            raise SemvprError(f"backbone weights {source} do not match DINOv2 ViT-B/14 (no {name!r})")
        self.load_state_dict(ours)

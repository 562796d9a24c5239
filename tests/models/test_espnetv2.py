"""ESPNetv2 (models.espnetv2) against a re-derivation written here in plain torch operations from the paper and
the authors' layer definitions (sacmehta/EdgeNets: EESP, DownSampler, EfficientPyrPool, EfficientPWConv), reading
the same weights by the authors' key names; the released files' refusals; the shared Cityscapes file on a real
CamVid frame."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from semvpr.core.errors import SemvprError
from semvpr.models.espnetv2 import load_espnetv2
from tests.helpers import REALDATA, espnetv2_state

ESPNET = REALDATA / "segmenters" / "espnetv2"
S1_WIDTHS = [32, 64, 128, 256]


# ------------------------------------------------------------------------------------------- the re-derivation
class Reference:
    """The network as a function of a state dict (BatchNorm in inference: (x - mean) / sqrt(var + 1e-5))."""

    def __init__(self, state: dict[str, Tensor], reversed_dilations: bool = False) -> None:
        self.w = {k: v.double() for k, v in state.items()}
        self.reversed_dilations = reversed_dilations

    def bn(self, x: Tensor, key: str) -> Tensor:
        w = self.w
        scale = w[f"{key}.weight"] / torch.sqrt(w[f"{key}.running_var"] + 1e-5)
        shift = w[f"{key}.bias"] - w[f"{key}.running_mean"] * scale
        return x * scale.view(1, -1, 1, 1) + shift.view(1, -1, 1, 1)

    def prelu(self, x: Tensor, key: str) -> Tensor:
        return torch.where(x >= 0, x, x * self.w[key].view(1, -1, 1, 1))

    def conv(self, x: Tensor, key: str, stride: int = 1, dilation: int = 1, bias: bool = False) -> Tensor:
        weight = self.w[key]
        groups = x.shape[1] // weight.shape[1]
        pad = (weight.shape[-1] // 2) * dilation
        b = self.w[key.replace(".weight", ".bias")] if bias else None
        return F.conv2d(x, weight, b, stride, pad, dilation, groups)

    def cbr(self, x: Tensor, key: str, stride: int = 1, act: bool = True) -> Tensor:
        """The encoder's CBR / CB: ``key.conv``, ``key.bn``, ``key.act``."""
        x = self.bn(self.conv(x, f"{key}.conv.weight", stride), f"{key}.bn")
        return self.prelu(x, f"{key}.act.weight") if act else x

    def seq_cbr(self, x: Tensor, key: str) -> Tensor:
        """The decoder's CBR: ``key.cbr.0`` conv, ``.1`` BatchNorm, ``.2`` PReLU."""
        return self.prelu(self.bn(self.conv(x, f"{key}.cbr.0.weight"), f"{key}.cbr.1"), f"{key}.cbr.2.weight")

    def eesp(self, x: Tensor, key: str, stride: int, r_lim: int) -> Tensor:
        """REDUCE (grouped 1x1), SPLIT/TRANSFORM (4 depthwise 3x3, dilations of receptive field 3, 5, 7, 9 capped
        at r_lim by 3, ascending), hierarchical feature fusion, MERGE (BR, grouped 1x1 CB), residual, PReLU."""
        reduced = self.cbr(x, f"{key}.proj_1x1")
        fields = sorted(k if k <= r_lim else 3 for k in (3, 5, 7, 9))
        rates = [{3: 1, 5: 2, 7: 3, 9: 4}[k] for k in fields]
        if self.reversed_dilations:
            rates = rates[::-1]
        outs = [self.conv(reduced, f"{key}.spp_dw.{i}.conv.weight", stride, d) for i, d in enumerate(rates)]
        fused = torch.cat([sum(outs[: i + 1]) for i in range(len(outs))], 1)
        fused = self.prelu(self.bn(fused, f"{key}.br_after_cat.bn"), f"{key}.br_after_cat.act.weight")
        expanded = self.bn(self.conv(fused, f"{key}.conv_1x1_exp.conv.weight"), f"{key}.conv_1x1_exp.bn")
        if stride == 2:
            return expanded
        if expanded.shape == x.shape:
            expanded = expanded + x
        return self.prelu(expanded, f"{key}.module_act.weight")

    def down(self, x: Tensor, image: Tensor, key: str, r_lim: int) -> Tensor:
        avg = F.avg_pool2d(x, 3, 2, 1)
        out = torch.cat([avg, self.eesp(x, f"{key}.eesp", 2, r_lim)], 1)
        while True:  # the image pooled until it is the output's size
            image = F.avg_pool2d(image, 3, 2, 1)
            if image.shape[2] == avg.shape[2]:
                break
        reinf = self.cbr(self.cbr(image, f"{key}.inp_reinf.0"), f"{key}.inp_reinf.1", act=False)
        return self.prelu(out + reinf, f"{key}.act.weight")

    def pyramid(self, x: Tensor, key: str, last: bool) -> Tensor:
        x = self.seq_cbr(x, f"{key}.projection_layer")
        h, w = x.shape[2:]
        maps = []
        for i, s in enumerate([2.0, 1.5, 1.0, 0.5, 0.1]):
            hs, ws = max(int(math.ceil(h * s)), 5), max(int(math.ceil(w * s)), 5)
            dw = f"{key}.stages.{i}.weight"
            if s < 1:
                m = F.interpolate(
                    self.conv(F.adaptive_avg_pool2d(x, (hs, ws)), dw), (h, w), mode="bilinear", align_corners=True
                )
            elif s > 1:
                m = F.adaptive_avg_pool2d(
                    self.conv(F.interpolate(x, (hs, ws), mode="bilinear", align_corners=True), dw), (h, w)
                )
            else:
                m = self.conv(x, dw)
            maps.append(m)
        out = torch.cat(maps, 1)
        out = self.prelu(self.bn(out, f"{key}.merge_layer.0.br.0"), f"{key}.merge_layer.0.br.1.weight")
        c = out.shape[1]
        order = [g * (c // 5) + i for i in range(c // 5) for g in range(5)]  # channel shuffle, 5 groups
        out = self.seq_cbr(out[:, order], f"{key}.merge_layer.2")
        out = self.conv(out, f"{key}.merge_layer.3.weight", bias=last)
        if last:
            return out
        return self.prelu(self.bn(out, f"{key}.br.br.0"), f"{key}.br.br.1.weight")

    def gated(self, x: Tensor, key: str) -> Tensor:
        gate = torch.sigmoid(self.conv(x.mean((2, 3), keepdim=True), f"{key}.wt_layer.1.weight"))
        return self.seq_cbr(x, f"{key}.expansion_layer") * gate

    def __call__(self, image: Tensor) -> Tensor:
        image = image.double()
        l1 = self.cbr(image, "base_net.level1", stride=2)
        l2 = self.down(l1, image, "base_net.level2_0", 13)
        l3 = self.down(l2, image, "base_net.level3_0", 11)
        for i in range(3):
            l3 = self.eesp(l3, f"base_net.level3.{i}", 1, 9)
        l4 = self.down(l3, image, "base_net.level4_0", 9)
        for i in range(7):
            l4 = self.eesp(l4, f"base_net.level4.{i}", 1, 7)
        out = self.pyramid(l4, "bu_dec_l1", False)
        for skip, n, dec in ((l3, 2, "bu_dec_l2"), (l2, 3, "bu_dec_l3"), (l1, 4, "bu_dec_l4")):
            up = F.interpolate(out, scale_factor=2, mode="bilinear", align_corners=True)
            merged = self.gated(skip, f"merge_enc_dec_l{n}") + up
            merged = self.prelu(self.bn(merged, f"bu_br_l{n}.0"), f"bu_br_l{n}.1.weight")
            out = self.pyramid(merged, dec, dec == "bu_dec_l4")
        return F.interpolate(out, image.shape[2:], mode="bilinear", align_corners=True)


def save(state: dict[str, Tensor], path: Path) -> Path:
    torch.save(state, path)
    return path


def normalised_image(size: tuple[int, int], seed: int = 1) -> Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn((1, 3, *size), generator=g)


# ------------------------------------------------------------------------------------------------------- tests
def test_the_network_is_the_re_derivation_at_1024x512(tmp_path: Path) -> None:
    state = espnetv2_state(S1_WIDTHS)
    model = load_espnetv2(save(state, tmp_path / "espnetv2_s_1.0_city.pth"))
    image = normalised_image((512, 1024))
    with torch.no_grad():
        mine, theirs = model(image).double(), Reference(state)(image)
    assert mine.shape == (1, 20, 512, 1024)
    assert theirs.std() > 0.05  # the logits carry the input's signal, not a vanishing net
    assert (mine - theirs).abs().max() < 1e-4  # float32 against the float64 re-derivation
    # A deliberate break (the branches' dilations in the wrong order) is seen by the same comparison.
    with torch.no_grad():
        broken = Reference(state, reversed_dilations=True)(image)
    assert (mine - broken).abs().max() > 1e-2


def test_the_width_and_depth_come_from_the_file(tmp_path: Path) -> None:
    widths = [16, 32, 64, 128]
    model = load_espnetv2(save(espnetv2_state(widths, seed=3), tmp_path / "narrow.pth"))
    assert [
        model.base_net.level1.conv.out_channels,
        *(m.act.num_parameters for m in (model.base_net.level2_0, model.base_net.level3_0, model.base_net.level4_0)),
    ] == widths
    with torch.no_grad():
        assert model(normalised_image((96, 160))).shape == (1, 20, 96, 160)


def test_odd_inference_sizes_are_decoded_to_the_input_size(tmp_path: Path) -> None:
    model = load_espnetv2(save(espnetv2_state(S1_WIDTHS), tmp_path / "s1.pth"))
    with torch.no_grad():
        assert model(normalised_image((97, 131))).shape == (1, 20, 97, 131)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda s: {
                ("eff_pool_16x16." + k.split(".", 1)[1] if k.startswith("bu_dec_l1.") else k): v for k, v in s.items()
            },
            "DiCENet",
        ),
        (
            lambda s: {
                **s,
                "bu_dec_l4.merge_layer.3.weight": torch.zeros(21, 10, 1, 1),
                "bu_dec_l4.merge_layer.3.bias": torch.zeros(21),
            },
            "21 classes (Pascal VOC",
        ),
        (lambda s: dict(list(s.items())[: len(s) // 2]), "incomplete"),
        (lambda s: {k: v for k, v in s.items() if not k.startswith("base_net.level4.6.")}, "lacks 24 of its keys"),
        (
            lambda s: (
                {k: v for k, v in s.items() if k.startswith("base_net.")}
                | {"classifier.weight": torch.zeros(1000, 1024)}
            ),
            "ImageNet classifier",
        ),
        (lambda s: {**s, "bu_br_l2.0.running_var": -torch.ones(64)}, "negative variance"),
        (lambda s: {**s, "base_net.level1.conv.weight": torch.full((32, 3, 3, 3), float("nan"))}, "not finite"),
        (lambda s: {**s, "bu_dec_l1.stages.0.weight": torch.zeros(10, 1, 5, 5)}, "(10, 1, 5, 5)"),
        (lambda s: {**s, "base_net.level1.bn.running_mean": torch.zeros(32, dtype=torch.long)}, "torch.int64"),
    ],
    ids=["dicenet", "pascal", "half-the-keys", "a-unit-short", "classifier", "variance", "nan", "shape", "int-weights"],
)
def test_a_file_of_another_kind_is_one_line_naming_it(tmp_path: Path, edit, message: str) -> None:
    path = save(edit(espnetv2_state(S1_WIDTHS)), tmp_path / "other.pth")
    with pytest.raises(SemvprError, match=None) as err:
        load_espnetv2(path)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_truncated_file_is_one_line(tmp_path: Path) -> None:
    path = save(espnetv2_state(S1_WIDTHS), tmp_path / "whole.pth")
    cut = tmp_path / "cut.pth"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(SemvprError, match="cut.pth is not a readable ESPNetv2 weights"):
        load_espnetv2(cut)


@pytest.mark.skipif(not ESPNET.is_dir(), reason="../shared/realdata absent")
@pytest.mark.parametrize("scale", ["1.0", pytest.param("2.0", marks=pytest.mark.slow)])
def test_the_released_file_is_the_re_derivation_and_segments_a_camvid_frame(scale: str) -> None:
    path = ESPNET / f"espnetv2_s_{scale}_city_1024x512.pth"
    state = torch.load(path, weights_only=True, map_location="cpu")
    model = load_espnetv2(path)
    frame = REALDATA / "camvid" / "test" / "0001TP_008550.jpg"
    rgb = np.asarray(Image.open(frame).convert("RGB").resize((1024, 512), Image.BILINEAR), dtype=np.float32) / 255
    mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
    image = torch.from_numpy(((rgb - mean) / std).astype(np.float32)).permute(2, 0, 1)[None]
    with torch.no_grad():
        mine, theirs = model(image), Reference(state)(image)
    assert (mine.double() - theirs).abs().max() < 1e-3  # float32 against float64 through 40 layers
    # CamVid's own labels, mapped to Cityscapes train ids (the shared README's table), agree on most pixels.
    camvid_to_city = np.array([10, 2, 5, 0, 1, 8, 7, 4, 13, 11, 12] + [255] * 245)
    truth = camvid_to_city[np.asarray(Image.open(REALDATA / "camvid" / "testannot" / "0001TP_008550.png"))]
    label = np.asarray(Image.fromarray(mine[0].argmax(0).byte().numpy()).resize(truth.shape[::-1], Image.NEAREST))
    known = truth != 255
    assert (label[known] == truth[known]).mean() > 0.75

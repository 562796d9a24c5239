"""Backbones: shapes/strides from the table, frozen/trainable split, weights loading errors."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torchvision

from semvpr.errors import SemvprError
from semvpr.models.backbones import ResNet50Backbone, VGG16Backbone
from tests.helpers import record_first_unit_batches

torch.set_num_threads(2)


@pytest.fixture(scope="module")
def vgg() -> VGG16Backbone:
    return VGG16Backbone(weights="none", train_from="conv5").eval()


def _check_table(model, outs: list[torch.Tensor], channels, strides, hw: tuple[int, int]) -> None:
    assert [o.shape[1] for o in outs] == list(channels)
    assert [(o.shape[2], o.shape[3]) for o in outs] == [(hw[0] // s, hw[1] // s) for s in strides]


def test_vgg16_shapes_and_split(vgg: VGG16Backbone) -> None:
    x = torch.rand(2, 3, 48, 64)
    outs = vgg(x)
    assert vgg.out_channels == 512 and vgg.skip_strides == (1, 2, 4, 8, 16)
    _check_table(vgg, outs, vgg.skip_channels, vgg.skip_strides, (48, 64))
    frozen = vgg.forward_frozen(x)
    # Frozen prefix: conv1_2..conv4_3 skips, then pool4 (the trainable part's input).
    assert vgg.frozen_channels == (64, 128, 256, 512, 512) and vgg.frozen_strides == (1, 2, 4, 8, 16)
    _check_table(vgg, frozen, vgg.frozen_channels, vgg.frozen_strides, (48, 64))
    torch.testing.assert_close(vgg.forward_trainable(frozen[-1]), outs[-1], rtol=0, atol=0)
    for a, b in zip(frozen[:4], outs[:4]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_vgg16_requires_grad_and_eval_split(vgg: VGG16Backbone) -> None:
    trainable = [n for n, p in vgg.named_parameters() if p.requires_grad]
    frozen = [n for n, p in vgg.named_parameters() if not p.requires_grad]
    assert sum(p.numel() for p in vgg.parameters() if p.requires_grad) == 3 * (512 * 512 * 9 + 512)
    assert len(trainable) == 6 and len(frozen) == 20
    vgg.train()
    assert all(not u.training for u in vgg.units[: vgg.split]) and all(u.training for u in vgg.units[vgg.split:])
    vgg.eval()


def test_vgg16_channels_last_and_other_splits(vgg: VGG16Backbone) -> None:
    x = torch.rand(1, 3, 32, 48)
    ref = vgg(x)[-1]
    out = vgg(x.contiguous(memory_format=torch.channels_last))[-1]
    torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-4)
    conv4 = VGG16Backbone(train_from="conv4").eval()
    conv4.load_state_dict(vgg.state_dict())
    frozen = conv4.forward_frozen(x)
    assert len(frozen) == 4 and frozen[-1].shape[1:] == (256, 4, 6)  # conv1..conv3 skips + pool3
    torch.testing.assert_close(conv4.forward_trainable(frozen[-1]), ref)
    frozen_all = VGG16Backbone(train_from=None).eval()
    frozen_all.load_state_dict(vgg.state_dict())
    assert not any(p.requires_grad for p in frozen_all.parameters())
    torch.testing.assert_close(frozen_all.forward_trainable(frozen_all.forward_frozen(x)[-1]), ref)


@pytest.mark.parametrize("stage,channels,strides", [
    ("layer3", (64, 256, 512, 1024), (2, 4, 8, 16)),
    ("layer4", (64, 256, 512, 1024, 2048), (2, 4, 8, 16, 32)),
])
def test_resnet50_shapes_and_split(stage: str, channels: tuple[int, ...], strides: tuple[int, ...]) -> None:
    model = ResNet50Backbone(stage=stage, train_from="layer3").eval()
    assert model.skip_channels == channels and model.skip_strides == strides and model.out_channels == channels[-1]
    x = torch.rand(2, 3, 64, 64)
    outs = model(x)
    _check_table(model, outs, channels, strides, (64, 64))
    frozen = model.forward_frozen(x)
    assert model.frozen_channels == (64, 256, 512)
    _check_table(model, frozen, model.frozen_channels, model.frozen_strides, (64, 64))
    torch.testing.assert_close(model.forward_trainable(frozen[-1]), outs[-1], rtol=0, atol=0)
    assert all(not p.requires_grad for n, p in model.named_parameters() if n.startswith(("units.0.", "units.2.", "units.3.")))
    assert all(p.requires_grad for n, p in model.named_parameters() if n.startswith("units.4."))
    model.train()
    assert not model.units[0][1].training and model.units[4].training  # frozen BatchNorm keeps its statistics


def test_missing_imagenet_weights_offline(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    for build, name in ((lambda: VGG16Backbone(weights="imagenet"), "vgg16-397923af.pth"),
                        (lambda: ResNet50Backbone(weights="imagenet"), "resnet50-0676ba61.pth")):
        with pytest.raises(SemvprError) as err:
            build()
        msg = str(err.value)
        assert "\n" not in msg and name in msg and str(tmp_path) in msg and "backbone.weights=none" in msg
    assert not any(tmp_path.rglob("*.pth"))  # nothing was downloaded


def test_weights_from_path(tmp_path: Path, vgg: VGG16Backbone) -> None:
    src = torchvision.models.vgg.make_layers(torchvision.models.vgg.cfgs["D"])
    path = tmp_path / "vgg_features.pth"
    # A torchvision vgg16 state dict without the classifier (which is not needed and 0.5 GB).
    torch.save({f"features.{k}": v for k, v in src.state_dict().items()}, path)
    loaded = VGG16Backbone(weights=path)
    torch.testing.assert_close(loaded.units[8][4].weight, src[28].weight, rtol=0, atol=0)
    with pytest.raises(SemvprError, match="does not exist"):
        VGG16Backbone(weights=tmp_path / "nope.pth")
    torch.save({"features.0.weight": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(SemvprError, match="do not fit torchvision vgg16"):
        VGG16Backbone(weights=tmp_path / "bad.pth")
    with pytest.raises(SemvprError, match="train_from"):
        VGG16Backbone(train_from="conv9")



def _imagenet_normalise(x: torch.Tensor) -> torch.Tensor:
    """What the references' input transform does (our backbones normalise inside forward)."""
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    return (x - mean) / std


def test_vgg16_cut_matches_the_references() -> None:
    # pytorch-NetVlad and the VPR benchmark: layers = list(vgg16().features.children())[:-2], i.e. up
    # to conv5_3 without its ReLU and pool5; they train layers[-5:] (conv5_1 … conv5_3).
    layers = list(torchvision.models.vgg16().features.children())[:-2]
    assert len(layers) == 29 and isinstance(layers[-1], torch.nn.Conv2d)
    reference = torch.nn.Sequential(*layers).eval()
    ours = VGG16Backbone(weights="none", train_from="conv5").eval()
    # Load the reference's weights by torchvision index: the two agree on every layer's position.
    ours.load_state_dict(_vgg_units_state(reference.state_dict()))
    x = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        expected, out = reference(_imagenet_normalise(x)), ours(x)[-1]
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-5)
    assert (out < 0).any()  # before the ReLU: signed local features
    trainable = sum(p.numel() for p in ours.parameters() if p.requires_grad)
    assert trainable == sum(p.numel() for layer in layers[-5:] for p in layer.parameters())


def _vgg_units_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """torchvision features.<i>.* names → our units.<unit>.<offset>.* names (unit ranges by index)."""
    starts = (0, 4, 5, 9, 10, 16, 17, 23, 24)
    out = {}
    for key, value in state.items():
        index, rest = key.split(".", 1)
        unit = max(u for u, s in enumerate(starts) if s <= int(index))
        out[f"units.{unit}.{int(index) - starts[unit]}.{rest}"] = value
    return out


def test_resnet50_cut_matches_the_benchmark() -> None:
    # deep-visual-geo-localization-benchmark, backbone=resnet50conv4: list(resnet50().children())[:-3]
    # (conv1, bn1, relu, maxpool, layer1, layer2, layer3); children before layer3 frozen.
    resnet = torchvision.models.resnet50().eval()
    reference = torch.nn.Sequential(*list(resnet.children())[:-3]).eval()
    ours = ResNet50Backbone(stage="layer3", weights="none", train_from="layer3").eval()
    prefixes = {"conv1.": "units.0.0.", "bn1.": "units.0.1.", "layer1.": "units.2.", "layer2.": "units.3.",
                "layer3.": "units.4."}
    state = {prefixes[p] + k[len(p):]: v for k, v in resnet.state_dict().items()
             for p in prefixes if k.startswith(p)}
    ours.load_state_dict(state, strict=True)
    x = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        torch.testing.assert_close(ours(x)[-1], reference(_imagenet_normalise(x)), rtol=1e-5, atol=1e-5)
    trainable = {n.split(".")[1] for n, p in ours.named_parameters() if p.requires_grad}
    assert trainable == {"4"}  # layer3 only, as the benchmark's resnet50conv4


def test_large_batches_run_in_chunks_with_the_same_outputs(monkeypatch: pytest.MonkeyPatch) -> None:
    import semvpr.models.backbones as backbones

    model = VGG16Backbone(weights="none", train_from="conv5").eval().to(memory_format=torch.channels_last)
    x = torch.rand(5, 3, 48, 64).contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        whole = model.forward_frozen(x)
    # Per 48x64 image, derived from VGG16's layout (not from the module): the widest frozen activation
    # is conv1 (64 channels at stride 1), counted 4x; the kept outputs are conv1..conv4 and pool4.
    kept = 64 + 128 / 2**2 + 256 / 4**2 + 512 / 8**2 + 512 / 16**2
    per_image = 4 * (4 * 64 + kept) * 48 * 64
    monkeypatch.setattr(backbones, "FORWARD_BYTES", int(2.5 * per_image))
    assert model.images_per_forward((48, 64)) == 2
    assert model.images_per_forward((48, 64), keep_scales=False) == int(2.5 * per_image // (4 * 4 * 64 * 48 * 64))
    seen = record_first_unit_batches(model)
    with torch.no_grad():
        chunked = model.forward_frozen(x)
        assert seen == [2, 2, 1]
        for a, b in zip(chunked, whole, strict=True):
            # oneDNN may pick another kernel for another batch size: equal up to float rounding.
            torch.testing.assert_close(a, b)
        last = model.forward_frozen(x, keep_scales=False)
    assert len(last) == 1
    torch.testing.assert_close(last[0], whole[-1])
    monkeypatch.setattr(backbones, "FORWARD_BYTES", 1)
    assert model.images_per_forward((48, 64)) == 1  # never zero images per pass

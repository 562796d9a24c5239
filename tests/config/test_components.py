"""Every component that ``conf/`` names, found from the config files (no hand-written list): it builds
through the one builder, is the kind of class its group requires, and keeps its group's contract.

Aggregators: weights of 1 everywhere are the unmasked output, a location of weight 0 has no influence,
and an image whose mask keeps nothing is described unmasked. Mask sources: a (B,1,h,w) binary or
(B,C,h,w) learned grid mask. Backbones: the channels and strides their tables declare."""

from __future__ import annotations

import inspect
import re

import pytest
import torch
from omegaconf import OmegaConf, open_dict

from semvpr.config.build import build_backbone, build_mask_source
from semvpr.config.components import COMPONENTS, build_component, component_class, node_class, options
from semvpr.config.plan import mask_plan
from semvpr.core.errors import SemvprError
from semvpr.data.classes import NUM_CLASSES
from semvpr.models.aggregators.base import Aggregator
from tests.helpers import config

torch.set_num_threads(2)
D, H, W = 32, 4, 5
#: Variants beyond the shipped files, as overrides of them.
AGGREGATOR_VARIANTS = {
    "gem (plain)": ("gem", ["aggregator.fc_dim=null"]),
    "boq (1x1)": ("boq", ["aggregator.proj_kernel=1"]),
    "boq (3x3)": ("boq", ["aggregator.proj_kernel=3"]),
}
AGGREGATORS = {name: (name, []) for name in options("aggregator")} | AGGREGATOR_VARIANTS


def test_every_group_has_components_and_each_names_its_kind_of_class() -> None:
    for group, spec in COMPONENTS.items():
        names = options(group)
        assert len(names) >= 3, (group, names)
        for name in names:
            cls = component_class(config(f"{group}={name}"), group)
            assert cls is None or issubclass(cls, spec.base), (group, name, cls)
    assert {"netvlad", "sral", "gem", "mixvpr", "salad", "boq"} <= set(options("aggregator"))


def test_a_group_setting_is_never_a_parameter_of_its_class() -> None:
    """A group's own settings are left out of its class's values (``build_component``): none may be a name the
    class takes, or a value set there would never reach it."""
    for group, spec in COMPONENTS.items():
        for name in options(group):
            cls = component_class(config(f"{group}={name}"), group)
            if cls is not None:
                assert not set(spec.settings) & set(inspect.signature(cls).parameters), (group, name)


def test_a_key_that_is_neither_a_class_value_nor_a_group_setting_is_one_line() -> None:
    """A key added to a component's file (or an experiment file) that its class does not take is refused as
    the class is looked up (check_config), not left unread."""
    node = config("aggregator=gem").aggregator
    component_class(config("aggregator=gem"), "aggregator")  # the shipped file passes
    with open_dict(node):
        node.fc_dimm = 256
    with pytest.raises(
        SemvprError, match=r"^aggregator\.fc_dimm is not a setting of aggregator=gem: .*GeM takes .*fc_dim"
    ):
        node_class(node, "aggregator")
    with pytest.raises(SemvprError, match=r"aggregator\.fc_dimm is not a setting"):
        build_component(node, "aggregator", dim=8)


@pytest.mark.parametrize(("aggregator", "key"), [("netvlad", "model.num_clusters"), ("gem", "aggregator.fc_dim")])
def test_an_unset_component_value_is_one_line_naming_the_key_to_set(aggregator: str, key: str) -> None:
    """A value left ``???``, in the component's node (GeM's ``fc_dim``) or where it interpolates from (NetVLAD's
    ``num_clusters: ${model.num_clusters}``), names the setting to pass."""
    cfg = config(f"aggregator={aggregator}")
    OmegaConf.update(cfg, key, "???")
    with pytest.raises(SemvprError, match=rf"^{re.escape(key)} is not set; pass it on the command line"):
        build_component(cfg.aggregator, "aggregator", dim=8)


@pytest.mark.parametrize("command", ["train", "eval", "localize"])
@pytest.mark.parametrize("name", options("aggregator"))
def test_every_aggregator_file_resolves_under_every_command(name: str, command: str) -> None:
    # eval and localize compose no recipe: an aggregator's file may not lean on one (its recipe=gsv
    # schedule is spelled out, not interpolated from recipe.default).
    node = config(f"aggregator={name}", config_name=command).aggregator
    assert OmegaConf.to_container(node, resolve=True)["name"] == name


def build_aggregator(name: str) -> Aggregator:
    """The aggregator of ``conf/aggregator/<file>.yaml`` (with the variant's overrides) for D channels on an
    HxW grid, initialised from a random sample where its class asks for one."""
    file, overrides = AGGREGATORS[name]
    cfg = config(f"aggregator={file}", "experiment=tiny", *overrides)
    node = cfg.aggregator
    extra = {"grid": [H, W]} if "grid" in node else {}
    torch.manual_seed(0)
    agg = build_component(node, "aggregator", dim=D, **extra).eval()
    assert isinstance(agg, Aggregator)
    if agg.init_sample != "none":  # shadows / centroids near real features, so assignments vary
        feats = torch.randn(400, D)
        agg.init_from_sample(feats, torch.arange(400) % 3 != 0 if agg.init_sample == "labelled" else None, seed=0)
    return agg


@pytest.mark.parametrize("name", AGGREGATORS)
def test_unit_weights_equal_the_unmasked_output(name: str) -> None:
    agg, x = build_aggregator(name), torch.randn(2, D, H, W)
    with torch.no_grad():
        assert torch.equal(agg(x, torch.ones(2, 1, H, W)), agg(x))
        assert agg(x).shape == (2, agg.output_dim)


@pytest.mark.parametrize("name", AGGREGATORS)
def test_a_mask_that_keeps_nothing_gives_the_unmasked_descriptor(name: str) -> None:
    """An image masked everywhere is described unmasked, not by a zero (or undefined) descriptor, which
    would be the nearest database image of every query with no match closer than distance 1."""
    agg, x = build_aggregator(name), torch.randn(3, D, H, W)
    weights = torch.rand(3, 1, H, W) * 0.9 + 0.1
    weights[1] = 0.0
    with torch.no_grad():
        out, unmasked = agg(x, weights), agg(x)
        assert torch.isfinite(out).all()
        assert torch.allclose(out[1], unmasked[1], atol=1e-6)
        assert torch.linalg.vector_norm(out[1]) == pytest.approx(1.0, abs=1e-5)
        # the other images keep their masks: the same as described alone
        assert torch.allclose(out[[0, 2]], agg(x[[0, 2]], weights[[0, 2]]), atol=1e-6)
        assert not torch.allclose(out[0], unmasked[0], atol=1e-4)


#: Feature scale of the zero-weight test: trained-like activations, which give SALAD's cluster scores a
#: std of about 5 (unscaled random features give about 0.25, at which a leak stays below the tolerance).
TRAINED_SCALE = 20.0


@pytest.mark.parametrize("name", AGGREGATORS)
def test_zero_weight_location_has_no_influence(name: str) -> None:
    agg, x = build_aggregator(name), TRAINED_SCALE * torch.randn(2, D, H, W)
    weights = torch.rand(2, 1, H, W) * 0.9 + 0.1
    weights[:, :, 1, 2] = 0.0
    weights[1, :, 3, 0] = 0.0
    moved = x.clone()
    moved[:, :, 1, 2] += 5.0 * TRAINED_SCALE * torch.randn(2, D)
    moved[1, :, 3, 0] = -7.0 * TRAINED_SCALE
    with torch.no_grad():
        base, after = agg(x, weights), agg(moved, weights)
        torch.testing.assert_close(after, base, rtol=0, atol=1e-6)
        # ...while the same perturbation with weight 1 does change the descriptor (the test can fail)
        assert (agg(moved, torch.ones_like(weights)) - agg(x, torch.ones_like(weights))).abs().max() > 1e-3


@pytest.mark.parametrize("name", options("mask"))
def test_every_mask_source_gives_a_grid_mask(name: str, tmp_path) -> None:
    """Built untrained through the builder (the weights a checkpoint would load), it declares what it needs
    and maps images to a binary (B,1,h,w) mask and to (B,C,h,w) class probabilities on the grid."""
    cfg = config(f"mask={name}", "experiment=tiny", "backbone.weights=none")
    backbone = build_backbone(cfg.backbone, 0).eval()
    source = build_mask_source(mask_plan(cfg), backbone)
    if cfg.mask._target_ is None:
        assert source is None
        return
    assert source.needs in ("teacher", "student", "ground_truth")
    images = torch.rand(2, 3, 64, 80)
    labels = None
    if source.needs == "ground_truth":
        import numpy as np
        from PIL import Image

        labels = []
        for i in range(2):
            labels.append(tmp_path / f"{i}.png")
            Image.fromarray(np.random.default_rng(i).integers(0, NUM_CLASSES, (64, 80)).astype(np.uint8)).save(
                labels[-1]
            )
        assert not source.describes_new_images
    with torch.no_grad():
        skips = backbone.forward_frozen(images)
        binary = source.grid_mask(images, skips, labels, (4, 5), "binary")
        learned = source.grid_mask(images, skips, labels, (4, 5), "learned")
    assert binary.shape == (2, 1, 4, 5) and set(binary.unique().tolist()) <= {0.0, 1.0}
    assert learned.shape == (2, NUM_CLASSES, 4, 5) and torch.isfinite(learned).all()


@pytest.mark.parametrize("name", options("backbone"))
def test_every_backbone_gives_the_channels_and_strides_it_declares(name: str) -> None:
    cfg = config(f"backbone={name}", "backbone.weights=none")
    backbone = build_backbone(cfg.backbone, 0).eval()
    # Sides that every stride divides (16 and DINOv2's 14); a ViT's token maps hold one more row than its
    # grid (the class token's), so the strides are read off the width.
    with torch.no_grad():
        outs = backbone(torch.rand(1, 3, 112, 224))
        scales = backbone.forward_frozen(torch.rand(1, 3, 112, 224))
    assert outs[-1].shape[1] == backbone.out_channels
    assert [s.shape[1] for s in scales] == list(backbone.frozen_channels)
    assert [224 // s.shape[-1] for s in scales] == list(backbone.frozen_strides)

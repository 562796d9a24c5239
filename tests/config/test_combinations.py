"""Every backbone x experiment composes and takes one training step (tiny inputs, CPU)."""

from __future__ import annotations

import pytest
import torch

from semvpr.config.build import build_backbone, build_retriever
from semvpr.config.plan import settings_of
from semvpr.retrieval.losses import triplet_loss
from tests.helpers import config

BACKBONES = ("vgg16", "resnet50", "efficientnet_lite0")
# What each experiment trains from, per backbone (paper: the cut trunk's last block, as NetVLAD).
TRAIN_FROM = {
    None: {"vgg16": None, "resnet50": None, "efficientnet_lite0": None},
    "tiny": {"vgg16": None, "resnet50": None, "efficientnet_lite0": None},
    "paper": {"vgg16": "conv5", "resnet50": "layer3", "efficientnet_lite0": "stage4"},
}


@pytest.mark.parametrize("experiment", [None, "tiny", "paper"])
@pytest.mark.parametrize("backbone", BACKBONES)
def test_backbone_experiment_composes_and_steps(backbone: str, experiment: str | None) -> None:
    overrides = [f"backbone={backbone}"] + ([f"experiment={experiment}"] if experiment else [])
    cfg = config(*overrides)
    assert cfg.backbone.name == backbone and cfg.backbone.train_from == TRAIN_FROM[experiment][backbone]
    # The experiment's weights, except the torchvision files that tests cannot download.
    cfg.backbone.weights = "none" if backbone != "efficientnet_lite0" else cfg.backbone.weights
    torch.manual_seed(0)
    model = build_backbone(cfg.backbone, cfg.seed)
    retriever = build_retriever(settings_of(cfg, training=True), model, None)
    aggregator = retriever.aggregator
    optimizer = retriever.configure_optimizers()
    optimizer = optimizer["optimizer"] if isinstance(optimizer, dict) else optimizer
    images = torch.rand(4, 3, 64, 80)
    with torch.no_grad():
        trunk = model.forward_frozen(images, keep_scales=False)[-1]
    frozen = [p.detach().clone() for unit in model.units[: model.split] for p in unit.parameters()]
    trainable = [p.detach().clone() for unit in model.units[model.split :] for p in unit.parameters()]
    before = [p.detach().clone() for p in aggregator.parameters()]
    # query 0, positive 1, negatives 2 and 3; the positive is the query with a little noise.
    desc_in = torch.cat([trunk[:1], trunk[:1] + 0.05 * torch.randn_like(trunk[:1]), trunk[2:]])
    loss = triplet_loss(retriever.describe(desc_in, None), torch.tensor([[0, 1, 2, 3]]), cfg.recipe.margin)
    assert torch.isfinite(loss)
    optimizer.zero_grad()
    (loss + 1e-3 * sum(p.float().square().sum() for p in aggregator.parameters())).backward()
    optimizer.step()
    assert all(
        torch.equal(a, p) for a, p in zip(frozen, (p for u in model.units[: model.split] for p in u.parameters()))
    )
    moved = [
        not torch.equal(a, p)
        for a, p in zip(trainable, (p for u in model.units[model.split :] for p in u.parameters()))
    ]
    assert (cfg.backbone.train_from is None) == (not moved) and (not moved or any(moved))
    assert any(not torch.equal(a, p) for a, p in zip(before, aggregator.parameters()))

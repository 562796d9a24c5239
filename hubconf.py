"""torch.hub entry point: ``torch.hub.load(<semvpr repo dir>, "semvpr", ckpt=PATH, source="local")``.

Returns a module mapping a batch of ImageNet-normalised images (B, 3, H, W) to L2-normalised
descriptors (B, model.feature_dim), as VPR-methods-evaluation's models do; ``model.transform``
is its preprocessing (PIL image → normalised tensor, resized to ``image_size`` if given). The
checkpoint is loaded as ``semvpr.eval`` loads it (weights only, record validated) and computes eval's
descriptors: in eval's precision for it (an author's release file in fp32 unless
``overrides=["trainer.precision=..."]``), on the device the model is on (see ``semvpr.hub``).
"""

dependencies = ["torch", "torchvision", "hydra", "omegaconf"]


def semvpr(ckpt: str, image_size: list[int] | None = None, overrides: list[str] | None = None):
    """A semvpr checkpoint (``<run dir>/checkpoints/tested.ckpt``) as a descriptor model; ``overrides`` as
    ``semvpr.eval`` takes them (``["mask=student", "student.checkpoint=DIR"]``; ``ckpt="none"`` with
    ``["aggregator=gem"]``: no VPR training)."""
    from semvpr.hub import load_model

    return load_model(ckpt, image_size, overrides or ())

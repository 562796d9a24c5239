"""The authors' released weight files, read as data into semvpr's backbones and aggregators.

A release file is a state dict (or a dict holding one under ``state_dict``, as pytorch-NetVlad's
``checkpoint.pth.tar`` and Lightning's ``.ckpt``) read by ``core.checkpoint.read_weights``: weights only,
nothing in it is run. Its layout is recognised from its keys, or named (``ckpt_format=``). Each layout
fixes what the author's own evaluation fixes (model, key names, image size, how images are resized to it: PIL's
bilinear as most authors' torchvision transforms do on PIL images, Bag-of-Queries' bicubic with antialiasing on
the tensor):

- ``netvlad``: VGG16 ``features[:-2]`` (conv5_3, no ReLU) + NetVLAD, vladv1 (pytorch-NetVlad ``main.py``);
  ``encoder.N``, ``pool.conv``, ``pool.centroids``; the images' own size.
- ``mixvpr``: ResNet50 to ``layer3`` + MixVPR (MixVPR ``main.py`` ``VPRModel``); ``backbone.model.*``,
  ``aggregator.mix.I.mix.{0,1,3}``, ``aggregator.{channel,row}_proj``; 320 × 320.
- ``cosplace``, ``eigenplaces``: ResNet50 ``children()[:-2]`` + L2, GeM, Linear, L2 (``GeoLocalizationNet``);
  ``backbone.N``, ``aggregation.1.p``, ``aggregation.3``; the images' own size.
- ``boq``: ResNet50 to ``layer3`` + BoQ with its 3×3 projection (Bag-of-Queries ``hubconf.py``);
  ``backbone.net.N``, ``aggregator.{proj_c,norm_input,boqs.I,fc}``; 384 × 384, bicubic on the tensor.
- ``boq_dinov2``: DINOv2 ViT-B/14's patch tokens after its last block, without the final norm (Bag-of-Queries
  ``src/backbones.py`` ``DinoV2``) + BoQ with its 3×3 projection; ``backbone.dino.*`` in DINOv2's naming,
  ``aggregator.*`` as ``boq``; 322 × 322, bicubic on the tensor.
- ``salad``: DINOv2 ViT-B/14's normalised patch tokens and class token (SALAD ``models/backbones/dinov2.py``,
  ``return_token``, ``norm_layer``) + SALAD with the class token as its global token (``hubconf.py``);
  ``backbone.model.*`` in DINOv2's naming, ``aggregator.{token_features,cluster_features,score,dust_bin}``;
  322 × 322.

A layout's name is its project's; a project's release of another backbone adds the backbone's name
(``boq`` is Bag-of-Queries' ResNet50 file, ``boq_dinov2`` its DINOv2 one).

Every author normalises with the ImageNet mean and std (what semvpr's torchvision and DINOv2 backbones do) and
L2-normalises the descriptor (what every semvpr aggregator does); none of these releases ships a PCA.
CosPlace and EigenPlaces share one layout (the same network), so a file of that layout must be named.
pytorch-NetVlad's vladv1 assignment has no bias: semvpr's NetVLAD takes a zero one, and its α (used only to
initialise) is 0. ``map_release`` checks the mapped weights against the model built for them: a missing,
extra or mis-shaped key is one line naming it in the author's naming.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from semvpr.core.checkpoint import dtype_fault, read_weights, weight_fault, weights_in
from semvpr.core.errors import SemvprError
from semvpr.models.backbones import VGG16_SLICES
from semvpr.models.dinov2 import DINOV2_KEYS

#: ``ckpt_format=`` values: ``auto`` recognises a semvpr checkpoint or a release layout; ``semvpr`` only the former.
FORMATS = ("auto", "semvpr", "netvlad", "mixvpr", "cosplace", "eigenplaces", "boq", "boq_dinov2", "salad")
#: Up to how many blocks / mixers / convolutions a layout's numbered keys are mapped.
_MAX_INDEX = 64
#: semvpr's ResNet50 units as torchvision names them (``ResNet50Backbone``: the stem is one unit).
_RESNET_UNITS = {"conv1": "0.0", "bn1": "0.1", "layer1": "2", "layer2": "3", "layer3": "4", "layer4": "5"}
#: torchvision's ``resnet50().children()`` positions (a ``Sequential`` of them, as CosPlace and BoQ build it).
_RESNET_CHILDREN = {"0": "conv1", "1": "bn1", "4": "layer1", "5": "layer2", "6": "layer3", "7": "layer4"}


@dataclass(frozen=True)
class Layout:
    """An author's model and file layout: the semvpr backbone and aggregator choices it is, and how keys map."""

    name: str
    #: The descriptor's name in tables, e.g. ``mixvpr (ResNet50, released)``.
    label: str
    backbone: str
    aggregator: str
    #: (H, W) the author evaluates at; None: the images' own size (the data config's ``image_size``).
    image_size: tuple[int, int] | None
    #: (author's key prefix, semvpr's retriever key prefix), longest match first.
    prefixes: tuple[tuple[str, str], ...]
    #: Keys that tell this layout apart (all present).
    marks: tuple[str, ...]
    #: The semvpr settings the weights' shapes fix: backbone stage, the aggregator's values, model node.
    settings: Callable[[dict[str, Tensor]], dict[str, Any]]
    #: semvpr keys the author's model has no weight for, and the value that reproduces its forward pass.
    derived: Callable[[dict[str, Tensor]], dict[str, Tensor]] = field(default=lambda state: {})
    #: How the author's test transform resizes the images (``data.images.RESIZES``).
    resize: str = "bilinear"


@dataclass(frozen=True)
class Release:
    """A release file's weights (the author's names) and its layout."""

    path: Path
    layout: Layout
    state: dict[str, Tensor]

    @property
    def where(self) -> str:
        return f"release file {self.path} ({self.layout.name} layout)"

    def settings(self) -> dict[str, Any]:
        """``{"backbone": {...}, "aggregator": {...}, "model": {...}}`` settings the weights fix."""
        try:
            return self.layout.settings(self.state)
        except (KeyError, IndexError, ValueError) as err:
            raise SemvprError(f"{self.where}: cannot read the model's sizes ({type(err).__name__}: {err})") from None


def _resnet(author: str, children: bool) -> tuple[tuple[str, str], ...]:
    """Prefix pairs from an author's ResNet naming (``author`` + torchvision names, or + child positions)."""
    names = _RESNET_CHILDREN if children else {k: k for k in _RESNET_UNITS}
    return tuple((f"{author}{key}.", f"backbone.units.{_RESNET_UNITS[name]}.") for key, name in names.items())


def _vgg16(author: str) -> tuple[tuple[str, str], ...]:
    """``features[:29]`` positions → semvpr's VGG16 units (``VGG16_SLICES``)."""
    return tuple(
        (f"{author}{n}.", f"backbone.units.{unit}.{n - a}.")
        for unit, (a, b) in enumerate(VGG16_SLICES)
        for n in range(a, b)
    )


def _dinov2(author: str) -> tuple[tuple[str, str], ...]:
    """An author's DINOv2 module (``author`` + DINOv2's names) → semvpr's DINOv2 units (``DINOV2_KEYS``)."""
    return tuple((f"{author}{theirs}", f"backbone.{ours}") for theirs, ours in DINOV2_KEYS)


def _numbered(author: str, ours: str, parts: dict[str, str]) -> tuple[tuple[str, str], ...]:
    """``author{i}.{part}`` → ``ours{i}.{parts[part]}`` for every block index."""
    return tuple((f"{author}{i}.{a}", f"{ours}{i}.{b}") for i in range(_MAX_INDEX) for a, b in parts.items())


def _count(state: dict[str, Tensor], prefix: str) -> int:
    """How many consecutive blocks ``prefix{i}.`` the state holds."""
    n = 0
    while any(k.startswith(f"{prefix}{n}.") for k in state):
        n += 1
    return n


def _square(hw: int, where: str) -> list[int]:
    side = round(hw**0.5)
    if side * side != hw:
        raise ValueError(f"{where} has {hw} locations, not a square grid")
    return [side, side]


def _netvlad_settings(state: dict[str, Tensor]) -> dict[str, Any]:
    k = int(state["pool.centroids"].shape[0])
    return {"backbone": {}, "aggregator": {}, "model": {"num_clusters": k}}


def _netvlad_derived(state: dict[str, Tensor]) -> dict[str, Tensor]:
    derived = {"aggregator.alpha": torch.tensor(0.0)}
    if "pool.conv.bias" not in state:  # vladv1: softmax(w·x), no bias
        derived["aggregator.conv.bias"] = torch.zeros(state["pool.centroids"].shape[0])
    return derived


def _mixvpr_settings(state: dict[str, Tensor]) -> dict[str, Any]:
    hw = int(state["aggregator.row_proj.weight"].shape[1])
    values = {
        "grid": _square(hw, "aggregator.row_proj.weight"),
        "out_channels": int(state["aggregator.channel_proj.weight"].shape[0]),
        "out_rows": int(state["aggregator.row_proj.weight"].shape[0]),
        "mix_depth": _count(state, "aggregator.mix."),
        "mlp_ratio": float(state["aggregator.mix.0.mix.1.weight"].shape[0]) / hw,
    }
    return {"backbone": {"stage": "layer3"}, "aggregator": values, "model": {}}


def _gem_settings(state: dict[str, Tensor]) -> dict[str, Any]:
    stage = "layer4" if "backbone.7.0.conv1.weight" in state else "layer3"
    values = {"fc_dim": int(state["aggregation.3.weight"].shape[0])}
    return {"backbone": {"stage": stage}, "aggregator": values, "model": {}}


def _boq_settings(backbone: dict[str, Any]) -> Callable[[dict[str, Tensor]], dict[str, Any]]:
    """BoQ's sizes from its weights, on a trunk of the ``backbone`` settings."""

    def settings(state: dict[str, Tensor]) -> dict[str, Any]:
        queries = state["aggregator.boqs.0.queries"]
        values = {
            "proj_channels": int(queries.shape[2]),
            "num_queries": int(queries.shape[1]),
            "num_layers": _count(state, "aggregator.boqs."),
            "row_dim": int(state["aggregator.fc.weight"].shape[0]),
            "proj_kernel": int(state["aggregator.proj_c.weight"].shape[-1]),
        }
        return {"backbone": dict(backbone), "aggregator": values, "model": {}}

    return settings


def _salad_settings(state: dict[str, Tensor]) -> dict[str, Any]:
    """SALAD's sizes from its weights; its MLPs hold the authors' dropout (the module at index 1) and the
    Sinkhorn runs the authors' 3 iterations; the global token is DINOv2's class token."""
    values = {
        "cluster_dim": int(state["aggregator.cluster_features.3.weight"].shape[0]),
        "token_dim": int(state["aggregator.token_features.2.weight"].shape[0]),
        "hidden_dim": int(state["aggregator.token_features.0.weight"].shape[0]),
        "dropout": 0.3,
        "iters": 3,
        "global_token": "class",
    }
    clusters = int(state["aggregator.score.3.weight"].shape[0])
    return {"backbone": {"class_token": True}, "aggregator": values, "model": {"num_clusters": clusters}}


#: MixVPR's ``FeatureMixerLayer.mix`` (LayerNorm, Linear, ReLU, Linear) → semvpr's ``FeatureMixer``.
_MIXER = {"mix.0.": "norm.", "mix.1.": "fc1.", "mix.3.": "fc2."}
#: BoQ's head, named alike in both of its releases.
_BOQ = (
    ("aggregator.proj_c.", "aggregator.proj_c."),
    ("aggregator.norm_input.", "aggregator.norm_input."),
    ("aggregator.boqs.", "aggregator.blocks."),
    ("aggregator.fc.", "aggregator.fc."),
)
_GEM = (
    *_resnet("backbone.", children=True),
    ("aggregation.1.p", "aggregator.p"),
    ("aggregation.3.", "aggregator.fc."),
)

LAYOUTS: dict[str, Layout] = {
    layout.name: layout
    for layout in (
        Layout(
            "netvlad",
            "netvlad (VGG16, released)",
            "vgg16",
            "netvlad",
            None,
            (*_vgg16("encoder."), ("pool.conv.", "aggregator.conv."), ("pool.centroids", "aggregator.centroids")),
            ("encoder.0.weight", "pool.centroids"),
            _netvlad_settings,
            _netvlad_derived,
        ),
        Layout(
            "mixvpr",
            "mixvpr (ResNet50, released)",
            "resnet50",
            "mixvpr",
            (320, 320),
            (
                *_resnet("backbone.model.", children=False),
                *_numbered("aggregator.mix.", "aggregator.mix.", _MIXER),
                ("aggregator.channel_proj.", "aggregator.channel_proj."),
                ("aggregator.row_proj.", "aggregator.row_proj."),
            ),
            ("backbone.model.conv1.weight", "aggregator.channel_proj.weight"),
            _mixvpr_settings,
        ),
        *(  # one network (GeoLocalizationNet), released by two projects
            Layout(
                name,
                f"{name} (ResNet50, released)",
                "resnet50",
                "gem",
                None,
                _GEM,
                ("backbone.0.weight", "aggregation.1.p", "aggregation.3.weight"),
                _gem_settings,
            )
            for name in ("cosplace", "eigenplaces")
        ),
        Layout(
            "boq",
            "boq (ResNet50, released)",
            "resnet50",
            "boq",
            (384, 384),
            (*_resnet("backbone.net.", children=True), *_BOQ),
            ("backbone.net.0.weight", "aggregator.boqs.0.queries"),
            _boq_settings({"stage": "layer3"}),
            resize="bicubic",
        ),
        Layout(
            "boq_dinov2",
            "boq (DINOv2, released)",
            "dinov2_vitb14",
            "boq",
            (322, 322),
            (*_dinov2("backbone.dino."), *_BOQ),
            ("backbone.dino.cls_token", "aggregator.boqs.0.queries"),
            _boq_settings({"final_norm": False}),
            resize="bicubic",
        ),
        Layout(
            "salad",
            "salad (DINOv2, released)",
            "dinov2_vitb14",
            "salad",
            (322, 322),
            (*_dinov2("backbone.model."), ("aggregator.", "aggregator.")),
            ("backbone.model.cls_token", "aggregator.dust_bin"),
            _salad_settings,
        ),
    )
}


def recognise(state: dict[str, Tensor], path: Path) -> Layout:
    """The one layout whose marks the state holds; one line when none or several (CosPlace / EigenPlaces) do."""
    found = [layout for layout in LAYOUTS.values() if all(k in state for k in layout.marks)]
    names = sorted({layout.name for layout in found})
    if not found:
        first = next(iter(state), None)
        raise SemvprError(
            f"release file {path} has no layout semvpr reads (first key {first!r}); the layouts are "
            f"{', '.join(LAYOUTS)}: name one with ckpt_format=... if the file is one of them"
        )
    if len(found) > 1:
        raise SemvprError(
            f"release file {path} has the layout {' and '.join(names)} share (the same network): "
            f"name it, ckpt_format={' or ckpt_format='.join(names)}"
        )
    return found[0]


def weights_of(contents: Any, path: Path) -> dict[str, Tensor]:
    """The state dict in a release file's contents (``core.checkpoint.weights_in``: a training checkpoint's, or
    the contents themselves; keys without a DataParallel / DDP / ``torch.compile`` wrapper's names)."""
    state = weights_in(contents, f"release file {path}")
    if not isinstance(state, dict) or not state:
        raise SemvprError(f"release file {path} holds no state dict (got {type(contents).__name__})")
    for key, value in state.items():
        fault = weight_fault(key, value) or (
            f"has shape {tuple(value.shape)}: no weights" if value.numel() == 0 else None
        )
        if fault is not None:
            raise SemvprError(f"release file {path}: weight {key!r} {fault}; the file is damaged")
    return state


def read_release(path: str | Path, fmt: str = "auto", contents: Any = None) -> Release:
    """The release file at ``path`` (its ``contents`` if already read), its layout recognised or ``fmt``."""
    path = Path(path)
    if fmt not in FORMATS or fmt == "semvpr":
        raise SemvprError(f"ckpt_format={fmt!r} is not a release layout; one of {', '.join(('auto', *LAYOUTS))}")
    state = weights_of(read_weights(path, "release file") if contents is None else contents, path)
    layout = recognise(state, path) if fmt == "auto" else LAYOUTS[fmt]
    missing = next((k for k in layout.marks if k not in state), None)
    if missing is not None:
        raise SemvprError(f"release file {path} is not of the {fmt} layout: it has no {missing!r}")
    return Release(path, layout, state)


#: semvpr's backbone keys → the trunk's own naming, torchvision's or DINOv2's (what ``backbone.weights=FILE``
#: loads), per backbone choice.
_TRUNK_NAMING = {
    "resnet50": tuple((f"backbone.units.{unit}.", f"{name}.") for name, unit in _RESNET_UNITS.items()),
    "vgg16": tuple(
        (f"backbone.units.{unit}.{n - a}.", f"features.{n}.")
        for unit, (a, b) in enumerate(VGG16_SLICES)
        for n in range(a, b)
    ),
    "dinov2_vitb14": tuple((f"backbone.{ours}", theirs) for theirs, ours in DINOV2_KEYS),
}


def release_trunk(state: dict[str, Any], path: Path, arch: str) -> dict[str, Tensor] | None:
    """The trunk of a release file of an ``arch`` layout in the trunk's own naming, or None when ``state`` is of
    no release layout: ``backbone.weights=FILE`` then builds the release's trunk, and a student trained on it
    (``semvpr.segment``) decodes the trunk the release evaluates with."""
    layout = next((lo for lo in LAYOUTS.values() if lo.backbone == arch and all(k in state for k in lo.marks)), None)
    if layout is None:
        return None
    trunk = {}
    for key, value in weights_of(state, path).items():
        ours = rename(key, layout.prefixes)
        if ours is not None and ours.startswith("backbone."):
            trunk[rename(ours, _TRUNK_NAMING[arch]) or ours] = value
    return trunk


def rename(key: str, pairs: tuple[tuple[str, str], ...]) -> str | None:
    """``key`` with its longest matching prefix replaced, or None when none matches."""
    best = max((p for p in pairs if key.startswith(p[0])), key=lambda p: len(p[0]), default=None)
    return None if best is None else best[1] + key[len(best[0]) :]


def map_release(release: Release, expected: dict[str, Tensor]) -> dict[str, Tensor]:
    """The release's weights in the names of ``expected`` (the backbone's and aggregator's entries of the
    retriever's state dict, built for it), checked key by key: a key of the file the layout has no place
    for, a place the file has no weight for, a weight of another shape and one the model cannot hold in its dtype
    (``core.checkpoint.dtype_fault``) are each one line naming the key."""
    layout, where = release.layout, release.where
    pairs = layout.prefixes
    inverse = tuple((b, a) for a, b in pairs)
    out = dict(layout.derived(release.state))
    for key, value in release.state.items():
        target = rename(key, pairs)
        if target is None or target not in expected:
            raise SemvprError(f"{where}: key {key!r} is not part of the {layout.name} model")
        if target == "aggregator.p":  # CosPlace's GeM keeps p as a 1-element vector
            value = value.reshape(())
        if tuple(value.shape) != tuple(expected[target].shape):
            raise SemvprError(
                f"{where}: {key!r} has shape {tuple(value.shape)}, the {layout.name} model built from the file's "
                f"other weights needs {tuple(expected[target].shape)}"
            )
        if (why := dtype_fault(value, expected[target])) is not None:
            raise SemvprError(f"{where}: {key!r} {why}; the file is damaged")
        out[target] = value.to(expected[target].dtype)
    missing = sorted(set(expected) - set(out))
    if missing:
        raise SemvprError(f"{where}: no weight {rename(missing[0], inverse) or missing[0]!r}, which the model needs")
    return out

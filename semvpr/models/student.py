"""U-Net student: a small decoder over the frozen backbone prefix that predicts the teacher's classes.

It learns the Cityscapes classes of the teacher's pseudo-labels (cross-entropy, 19 outputs); its
static map is the sum of the static classes' probabilities, which is what the binary filter reads.
How it is trained (once, cached) is ``semvpr.segmentation.training``.

A trained student travels as a directory (``semvpr.segment`` writes ``<run>/student_<backbone>/``):
``model.safetensors`` (the weights) and ``student.json`` (its architecture, the frozen trunk it decodes
and the data it was trained on). :func:`load_student` reads one as data: no pickle, no code, known
keys only, the trunk and every weight's name and shape checked.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.errors import SemvprError
from semvpr.core.io import atomic_dir, read_json, regular_file, write_json
from semvpr.core.provenance import TrainedOn
from semvpr.core.spec import image_size, setting
from semvpr.data.classes import NUM_CLASSES, STATIC_NAMES, check_class_names
from semvpr.models.masks import static_vector
from semvpr.models.weights import check_tensor


@dataclass(frozen=True)
class StudentSpec:
    """The student's architecture and training settings (``conf/student/*.yaml``; ``config.plan.student_spec``)."""

    name: str = "unet"
    #: Strides of the frozen features it decodes (the output is at the smallest).
    strides: tuple[int, ...] = setting((4, 8, 16), low=1, high=64, also="a list of strides from 1 to 64")
    width: int = setting(32, low=1, high=4096)
    #: Pseudo-label classes that count as static (the binary target).
    static_classes: tuple[str, ...] = STATIC_NAMES
    epochs: int = setting(10, low=1)
    batch_size: int = setting(16, low=1)
    lr: float = setting(3.0e-3, above=True)
    weight_decay: float = setting(1.0e-4)
    bf16: bool = setting(True)
    num_workers: int = setting(2)
    #: Train on at most this many of the given images (a fixed random subset; None = all).
    max_images: int | None = setting(None, low=1, also="or null: all")
    #: Mirror a random half of each batch: the frozen features of each image's mirror image (one more trunk
    #: pass while the student is built; the student is cached) with its labels mirrored. Off: every step as
    #: without the option.
    flip: bool = setting(False)
    seed: int = 0
    #: A student directory saved by ``semvpr.segment`` (read by eval, localize and the hub); None = trained.
    checkpoint: str | None = None

    def __post_init__(self) -> None:
        """Its class names known, by the rule a saved student's ``student.json`` is read with (the fields' kinds
        and ranges are the schema's: ``config.schema.typed``)."""
        check_class_names(self.static_classes, "student.static_classes")


def _block(cin: int, cout: int) -> nn.Sequential:
    """conv3x3-BN-ReLU twice: the U-Net unit."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class Student(nn.Module):
    """Decoder from the deepest chosen frozen feature up through shallower skips to class logits."""

    def __init__(
        self,
        frozen_channels: Sequence[int],
        frozen_strides: Sequence[int],
        strides: Sequence[int] = (4, 8, 16),
        width: int = 64,
        static_names: Sequence[str] = STATIC_NAMES,
    ) -> None:
        super().__init__()
        self.register_buffer("static_weight", static_vector(static_names), persistent=False)
        # The deepest frozen output of each wanted stride (ResNet's stem and layer1 share none; VGG's do not).
        chosen = {s: i for i, s in enumerate(frozen_strides) if s in set(strides)}
        if not chosen:
            raise SemvprError(
                f"student.strides={list(strides)} match none of the backbone's frozen feature strides "
                f"{list(frozen_strides)}; pick some of those"
            )
        self.skip_indices = [chosen[s] for s in sorted(chosen)]  # shallow → deep
        self.out_stride = min(chosen)
        chans = [frozen_channels[i] for i in self.skip_indices]
        # 1x1 projections first: 3x3 convs on 256-512 raw channels cost ~7x more for no measured gain.
        self.lateral = nn.ModuleList(
            nn.Sequential(nn.Conv2d(c, width, 1, bias=False), nn.BatchNorm2d(width), nn.ReLU(inplace=True))
            for c in chans
        )
        self.bottom = _block(width, width)
        self.ups = nn.ModuleList(_block(2 * width, width) for _ in chans[:-1])
        self.head = nn.Conv2d(width, NUM_CLASSES, 1)

    def forward(self, skips: Sequence[Tensor]) -> Tensor:
        """Class logits (B,C,H/s,W/s) at the shallowest chosen stride, from ``forward_frozen`` outputs."""
        return self.decode([skips[i] for i in self.skip_indices])

    def decode(self, chosen: Sequence[Tensor]) -> Tensor:
        """Logits from just the chosen features (shallow → deep), e.g. a cache of them."""
        feats = [lateral(f.float()) for lateral, f in zip(self.lateral, chosen)]
        h = self.bottom(feats[-1])
        for f, block in zip(reversed(feats[:-1]), self.ups):
            h = F.interpolate(h, size=f.shape[-2:], mode="bilinear", align_corners=False)
            h = block(torch.cat([h, f], 1))
        return self.head(h)

    def class_prob(self, skips: Sequence[Tensor], out_hw: Sequence[int] | None = None) -> Tensor:
        """Softmax over the classes (B,C,·,·), optionally resized (bilinear) to ``out_hw``."""
        prob = torch.softmax(self.forward(skips).float(), dim=1)
        if out_hw is not None:
            prob = F.interpolate(prob, size=tuple(out_hw), mode="bilinear", align_corners=False)
        return prob

    def static_prob(self, skips: Sequence[Tensor], out_hw: Sequence[int] | None = None) -> Tensor:
        """Σ of the static classes' probabilities (B,1,·,·), optionally resized to ``out_hw``."""
        prob = torch.einsum("bchw,c->bhw", self.class_prob(skips, out_hw), self.static_weight)[:, None]
        return prob


def student_architecture(spec: StudentSpec, backbone: nn.Module) -> Student:
    """An untrained student of this spec over this backbone's frozen features (one line where they are not
    image-aligned maps)."""
    if not getattr(backbone, "image_maps", True):
        raise SemvprError(
            f"a student decodes a trunk's feature maps; {type(backbone).__name__}'s frozen outputs are token maps: "
            "use mask=teacher or mask=oracle with this backbone"
        )
    return Student(
        backbone.frozen_channels,
        backbone.frozen_strides,
        strides=list(spec.strides),
        width=int(spec.width),
        static_names=list(spec.static_classes),
    )


#: The files of a student directory; nothing else in it is read.
WEIGHTS_FILE, SPEC_FILE = "model.safetensors", "student.json"
STUDENT_FORMAT = 1
#: Files a student directory must not hold: code, and pickles (which can run code when loaded).
_REFUSED_SUFFIXES = {
    ".py": "code",
    ".pyc": "code",
    ".so": "code",
    ".pt": "a pickle",
    ".pth": "a pickle",
    ".bin": "a pickle",
    ".pkl": "a pickle",
    ".pickle": "a pickle",
    ".ckpt": "a pickle",
}
_SPEC_KEYS = {"format", "spec", "backbone", "image_size", "trained_on"}


def save_student(
    student: Student,
    spec: StudentSpec,
    backbone_name: str,
    backbone_identity: Mapping[str, Any],
    image_size: Sequence[int],
    trained_on: TrainedOn,
    out: Path,
) -> Path:
    """Write ``student`` as a directory :func:`load_student` reads: ``model.safetensors`` and
    ``student.json``; renamed into place when complete."""
    from safetensors.torch import save_file

    with atomic_dir(out) as tmp:
        save_file({k: v.detach().cpu().contiguous() for k, v in student.state_dict().items()}, tmp / WEIGHTS_FILE)
        write_json(
            tmp / SPEC_FILE,
            {
                "format": STUDENT_FORMAT,
                "spec": {
                    "strides": [int(s) for s in spec.strides],
                    "width": int(spec.width),
                    "static_classes": [str(c) for c in spec.static_classes],
                },
                "backbone": {"name": backbone_name, "frozen": dict(backbone_identity)},
                "image_size": [int(v) for v in image_size],
                "trained_on": trained_on.as_dict(),
            },
        )
    return out


def load_student(folder: str | Path, backbone: Any) -> Student:
    """The student saved in ``folder`` over ``backbone``'s frozen features, in eval mode; its training data
    in ``student.trained_on``. Refused in one line: a missing or foreign directory, code or pickles in it,
    a ``student.json`` with unknown keys or values, another frozen trunk than ``backbone``'s, weights whose
    names or shapes the recorded architecture does not have, or that are not finite."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    folder = Path(folder).expanduser()
    where = f"student directory {folder}"
    if not folder.is_dir():
        raise SemvprError(
            f"{where} {'is a file' if folder.exists() else 'not found'}; student.checkpoint=DIR names a student "
            "saved by semvpr.segment (<segment run>/student_<backbone>)"
        )
    inside = sorted(p for p in folder.glob("student_*") if (p / SPEC_FILE).is_file())
    if inside and not (folder / SPEC_FILE).exists():
        raise SemvprError(f"{where} is a semvpr.segment run; name a student in it: {' or '.join(map(str, inside))}")
    for path in sorted(folder.rglob("*")):
        kind = _REFUSED_SUFFIXES.get(path.suffix.lower())
        if kind is not None:
            raise SemvprError(
                f"{where} holds {path.relative_to(folder)} ({kind}); a student directory is {WEIGHTS_FILE} and "
                f"{SPEC_FILE} only, and nothing in it is run or unpickled"
            )
    record = _read_spec(folder / SPEC_FILE)
    spec, trunk = record["spec"], record["backbone"]
    identity = dict(backbone.frozen_identity())
    if trunk["frozen"] != identity:
        raise SemvprError(
            f"{where} decodes the frozen trunk of {trunk['name']} ({_trunk(trunk['frozen'])}); this model's is "
            f"{_trunk(identity)}: use a student trained on this backbone (semvpr.segment backbones=...)"
        )
    student = Student(
        backbone.frozen_channels,
        backbone.frozen_strides,
        strides=spec["strides"],
        width=spec["width"],
        static_names=spec["static_classes"],
    )
    weights = folder / WEIGHTS_FILE
    if not regular_file(weights, "student weights"):
        raise SemvprError(f"{where} has no {WEIGHTS_FILE} (only safetensors weights are read)")
    try:
        state = load_file(weights)
    except (SafetensorError, OSError, ValueError) as err:
        detail = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise SemvprError(f"{weights} is not readable safetensors ({detail})") from None
    expected = student.state_dict()
    missing, unexpected = sorted(set(expected) - set(state)), sorted(set(state) - set(expected))
    if missing or unexpected:
        first = f"lacks {missing[0]!r}, which" if missing else f"has {unexpected[0]!r}, which"
        raise SemvprError(
            f"{weights} {first} the architecture in {SPEC_FILE} {'has' if missing else 'does not have'} "
            f"({len(missing)} missing, {len(unexpected)} unexpected weights)"
        )
    for name, tensor in state.items():
        if tuple(tensor.shape) != tuple(expected[name].shape):
            raise SemvprError(
                f"{weights}: {name!r} is {list(tensor.shape)}, the architecture in {SPEC_FILE} makes "
                f"{list(expected[name].shape)}"
            )
        if tensor.dtype != expected[name].dtype:
            raise SemvprError(
                f"{weights}: {name!r} is {tensor.dtype}, the architecture in {SPEC_FILE} makes "
                f"{expected[name].dtype} (weights are never cast)"
            )
        check_tensor(tensor, name, weights)
    student.load_state_dict(state, strict=True)
    student.trained_on = TrainedOn.from_value(record["trained_on"], f"{folder / SPEC_FILE}: trained_on")  # type: ignore[attr-defined]
    return student.eval().requires_grad_(False)


def _trunk(identity: Mapping[str, Any]) -> str:
    return f"{identity.get('class')}, train_from={identity.get('train_from')}, weights {identity.get('frozen')}"


def _read_spec(path: Path) -> dict[str, Any]:
    """``student.json``, every key and value checked (a plain record of the project's own values)."""
    if not regular_file(path, "student record"):
        raise SemvprError(f"{path} not found; a student directory holds {SPEC_FILE} beside {WEIGHTS_FILE}")
    record = read_json(path, "student record")
    if not isinstance(record, dict):
        raise SemvprError(f"{path} is not a JSON object")
    unknown = sorted(set(record) - _SPEC_KEYS)
    if unknown:
        raise SemvprError(f"{path}: key {unknown[0]!r} is not part of a student record (keys: {sorted(_SPEC_KEYS)})")
    if record.get("format") != STUDENT_FORMAT:
        raise SemvprError(f"{path}: format={record.get('format')!r}, this semvpr reads format {STUDENT_FORMAT}")
    spec = record.get("spec")
    if not isinstance(spec, dict) or set(spec) != {"strides", "width", "static_classes"}:
        raise SemvprError(f"{path}: spec must hold exactly strides, width and static_classes")
    strides, width, classes = spec["strides"], spec["width"], spec["static_classes"]
    if not (isinstance(strides, list) and strides and all(_count(s, 64) for s in strides)):
        raise SemvprError(f"{path}: spec.strides={strides!r} is not a list of strides from 1 to 64")
    if not _count(width, 4096):
        raise SemvprError(f"{path}: spec.width={width!r} is not a whole number from 1 to 4096")
    check_class_names(classes, f"{path}: spec.static_classes")
    trunk = record.get("backbone")
    frozen = trunk.get("frozen") if isinstance(trunk, dict) else None
    if not (
        isinstance(trunk, dict)
        and set(trunk) == {"name", "frozen"}
        and isinstance(trunk["name"], str)
        and isinstance(frozen, dict)
        and set(frozen) == {"class", "train_from", "frozen"}
        and all(v is None or isinstance(v, str) for v in frozen.values())
    ):
        raise SemvprError(f"{path}: backbone must be {{'name': str, 'frozen': the trunk's frozen identity}}")
    image_size(record.get("image_size"), f"{path}: image_size")
    TrainedOn.from_value(record.get("trained_on"), f"{path}: trained_on")
    return record


def _count(value: Any, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= high

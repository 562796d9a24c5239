"""A teacher directory read as data, and the record ``semvpr.segment`` writes into one: a Mask2Former in
Hugging Face format (``config.json``, ``model.safetensors`` or ``pytorch_model.bin``,
``preprocessor_config.json``) from a local folder or a Hub id in the local cache, plus ``semvpr.json`` (the
size it trained at, the data it trained on) where ``semvpr.segment`` saved it. Nothing in a directory is
run: every file is checked before a class is built from it (docs/trust.md)."""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from transformers import Mask2FormerConfig, Mask2FormerForUniversalSegmentation, SwinConfig, TimmBackboneConfig

from semvpr.core.cache import config_hash
from semvpr.core.errors import SemvprError
from semvpr.core.io import read_json, regular_file, write_json
from semvpr.core.logs import no_hf_progress_bars, quiet_third_party
from semvpr.core.provenance import TrainedOn
from semvpr.core.spec import MAX_IMAGE_SIDE, float32_number, image_size
from semvpr.models.backbones import IMAGENET_MEAN, IMAGENET_STD
from semvpr.models.espnetv2 import CITYSCAPES_CHANNELS, load_espnetv2
from semvpr.models.teacher import Teacher, TeacherSpec, check_size, embedded_teacher, teacher_options
from semvpr.models.weights import check_tensor

#: Pixel-level backbones a teacher's config.json may name, and the keys their config may hold: those of
#: the config class (transformers' defaults) and of the older PretrainedConfig releases, plain values only.
BACKBONE_TYPES = {"swin": SwinConfig, "timm_backbone": TimmBackboneConfig}
LEGACY_CONFIG_KEYS = frozenset(
    [
        "add_cross_attention",
        "bad_words_ids",
        "begin_suppress_tokens",
        "bos_token_id",
        "chunk_size_feed_forward",
        "cross_attention_hidden_size",
        "decoder_start_token_id",
        "diversity_penalty",
        "do_sample",
        "early_stopping",
        "encoder_no_repeat_ngram_size",
        "eos_token_id",
        "exponential_decay_length_penalty",
        "finetuning_task",
        "forced_bos_token_id",
        "forced_eos_token_id",
        "is_decoder",
        "is_encoder_decoder",
        "length_penalty",
        "max_length",
        "min_length",
        "no_repeat_ngram_size",
        "num_beam_groups",
        "num_beams",
        "num_return_sequences",
        "output_attentions",
        "output_hidden_states",
        "output_scores",
        "pad_token_id",
        "prefix",
        "problem_type",
        "pruned_heads",
        "remove_invalid_values",
        "repetition_penalty",
        "return_dict",
        "return_dict_in_generate",
        "sep_token_id",
        "suppress_tokens",
        "task_specific_params",
        "temperature",
        "tf_legacy_loss",
        "tie_encoder_decoder",
        "tie_word_embeddings",
        "tokenizer_class",
        "top_k",
        "top_p",
        "torch_dtype",
        "dtype",
        "torchscript",
        "transformers_version",
        "typical_p",
        "use_bfloat16",
        "architectures",
        "_name_or_path",
        "path_norm",
        "id2label",
        "label2id",
        # what a backbone config records once its backbone is built (transformers' BackboneConfigMixin)
        "stage_names",
        "out_features",
        "out_indices",
        "_out_features",
        "_out_indices",
    ]
)
#: A timm model name: no ``local-dir:`` / ``hf-hub:`` prefix, no path.
_TIMM_NAME = re.compile(r"^[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)?$")
#: Model dtypes a config.json may record: the teacher runs in float32.
CONFIG_DTYPES = (None, "float32")


def check_config_values(data: Mapping[str, Any], path: Path) -> None:
    """A teacher's config.json, checked as command-line values are before any class is built: every
    number finite as a float32; sizes bounded (``MODEL_LIMITS``); ``dtype`` float32 or none; mappings
    only where a config has them (the label maps, ``backbone_config``), and ``backbone_config`` a Swin or
    timm backbone of allow-listed keys, plain values, its timm name a plain name (``local-dir:`` or
    ``hf-hub:`` would make timm read a file or the network) and nothing pretrained."""
    _check_plain(data, path, "")
    for key, value in data.items():
        check_size(key, value, str(path))
        if isinstance(value, dict) and key not in ("backbone_config", "id2label", "label2id"):
            raise SemvprError(f"{path}: {key} is a mapping; a Mask2Former config has none there")
    for key in ("dtype", "torch_dtype"):
        if data.get(key) not in CONFIG_DTYPES:
            raise SemvprError(f"{path}: {key}={data.get(key)!r}; the teacher runs in float32 (float32 or null)")
    backbone = data.get("backbone_config")
    if backbone is None:
        return
    where = f"{path}: backbone_config"
    kind = backbone.get("model_type") if isinstance(backbone, dict) else None
    if kind not in BACKBONE_TYPES:
        raise SemvprError(f"{where}.model_type={kind!r} is not one of {sorted(BACKBONE_TYPES)}")
    allowed = set(BACKBONE_TYPES[kind]().to_dict()) | LEGACY_CONFIG_KEYS
    for key, value in backbone.items():
        if key not in allowed:
            raise SemvprError(f"{where}.{key} is not a key of a {kind} config; only known keys are read")
        if isinstance(value, dict) and key not in ("id2label", "label2id", "task_specific_params", "pruned_heads"):
            raise SemvprError(f"{where}.{key} is a mapping; only plain values are read")
        check_size(key, value, where)
    if kind == "timm_backbone" and not (
        isinstance(backbone.get("backbone"), str) and _TIMM_NAME.match(backbone["backbone"])
    ):
        raise SemvprError(f"{where}.backbone={backbone.get('backbone')!r} is not a plain timm model name")
    if backbone.get("use_pretrained_backbone") or backbone.get("image_size", 1) not in range(1, MAX_IMAGE_SIDE + 1):
        raise SemvprError(
            f"{where}: use_pretrained_backbone={backbone.get('use_pretrained_backbone')!r}, "
            f"image_size={backbone.get('image_size')!r}; only self-contained weights and sizes up to {MAX_IMAGE_SIDE}"
        )


def _check_plain(node: Any, path: Path, at: str) -> None:
    """Every number in a JSON value finite as a float32 (``1e308`` is finite in float64 only)."""
    stack = [(node, at)]
    while stack:
        item, key = stack.pop()
        if isinstance(item, dict):
            stack.extend((v, f"{key}.{k}" if key else str(k)) for k, v in item.items())
        elif isinstance(item, list):
            stack.extend((v, f"{key}[{i}]") for i, v in enumerate(item))
        elif isinstance(item, int | float) and not isinstance(item, bool) and not float32_number(item):
            raise SemvprError(f"{path}: {key}={item!r} is not a finite float32 number")


#: Processor types whose normalisation is image_mean / image_std after a 1/255 rescale.
PROCESSOR_TYPES = (
    "Mask2FormerImageProcessor",
    "Mask2FormerImageProcessorFast",
    "MaskFormerImageProcessor",
    "MaskFormerImageProcessorFast",
)
WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")


def load_pretrained(checkpoint: str, **kwargs: Any) -> Teacher:
    """Load a Mask2Former checkpoint (HF id from the local cache, or a directory) as data.

    Nothing in the directory is run or asked about: its ``config.json`` must describe a plain
    Mask2Former (``model_type`` mask2former, no ``auto_map``), the weights are read from
    ``model.safetensors`` (or ``pytorch_model.bin`` with a weights-only load), and the image
    normalisation comes from ``preprocessor_config.json`` (ImageNet's when there is none). A directory
    written by ``semvpr.segment`` also holds ``semvpr.json`` (:func:`write_teacher_record`): the size the
    teacher was trained at, its inference size unless ``inference_size`` is given, and its training data.
    """
    folder = _checkpoint_dir(checkpoint)
    config = _mask2former_config(folder)
    record = read_teacher_record(folder)
    if record is not None and kwargs.get("inference_size") is None:
        kwargs["inference_size"] = record["image_size"]
    weights = next((folder / name for name in WEIGHT_FILES if regular_file(folder / name, "teacher weights")), None)
    if weights is None:
        raise SemvprError(
            f"teacher checkpoint {folder} has none of {list(WEIGHT_FILES)} (sharded or other weight files are not read)"
        )
    try:
        with no_hf_progress_bars():
            model = Mask2FormerForUniversalSegmentation.from_pretrained(
                folder,
                config=config,
                local_files_only=True,
                use_safetensors=weights.suffix == ".safetensors",
                trust_remote_code=False,
            )
    except Exception as err:  # noqa: BLE001 - any unreadable weight file gets the same one line
        raise SemvprError(
            f"teacher weights {weights} are unreadable ({type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''})"
        ) from None
    check_loaded_weights(model, weights)
    mean, std = _normalisation(folder)
    teacher = Teacher(model, image_mean=mean, image_std=std, **kwargs)
    # What makes its predictions: the bytes of its weights and config, and the normalisation.
    teacher.source_hash = config_hash([file_hash(weights), file_hash(folder / "config.json"), mean, std])
    if record is not None:
        teacher.trained_on = record["trained_on"]
    return teacher


def check_loaded_weights(model: nn.Module, weights: Path) -> None:
    """The weights as loaded from ``weights``: each tensor the file holds of the kind the model has (a
    float where the model has a float, an integer where it has one: no silent int to float cast), every
    float finite, every BatchNorm ``running_var`` >= 0."""
    state = model.state_dict()
    for name, is_float in _file_kinds(weights).items():
        if name in state and state[name].is_floating_point() != is_float:
            raise SemvprError(
                f"{weights}: {name!r} is {'a float' if is_float else 'an integer'} tensor where the model has "
                f"{state[name].dtype}; the weights are not this model's"
            )
    for name, tensor in state.items():
        check_tensor(tensor, name, weights)


def _file_kinds(weights: Path) -> dict[str, bool]:
    """Whether each tensor a weight file holds is a float (read from the safetensors header, or from a
    weights-only, memory-mapped load)."""
    if weights.suffix == ".safetensors":
        from safetensors import safe_open

        with safe_open(str(weights), framework="pt") as handle:
            return {k: handle.get_slice(k).get_dtype() in ("F16", "BF16", "F32", "F64") for k in handle.keys()}  # noqa: SIM118 - not a dict
    state = torch.load(weights, map_location="cpu", weights_only=True, mmap=True)
    return {k: v.is_floating_point() for k, v in state.items() if isinstance(v, Tensor)}


#: What ``semvpr.segment`` writes beside a teacher's Hugging Face files.
TEACHER_RECORD = "semvpr.json"
TEACHER_RECORD_FORMAT = 1


def write_teacher_record(folder: Path, image_size: Sequence[int], trained_on: TrainedOn) -> None:
    """``semvpr.json`` in a teacher directory: the size it was trained at and the data it was trained on."""
    write_json(
        folder / TEACHER_RECORD,
        {
            "format": TEACHER_RECORD_FORMAT,
            "image_size": [int(v) for v in image_size],
            "trained_on": trained_on.as_dict(),
        },
    )


def read_teacher_record(folder: Path) -> dict[str, Any] | None:
    """A teacher directory's ``semvpr.json`` checked (``image_size`` a list, ``trained_on`` a
    :class:`TrainedOn`), or None where there is none (a Hub checkpoint)."""
    path = folder / TEACHER_RECORD
    if not regular_file(path, "teacher file"):
        return None
    data = _read_json(path)
    if set(data) != {"format", "image_size", "trained_on"} or data["format"] != TEACHER_RECORD_FORMAT:
        raise SemvprError(
            f"{path}: expected exactly format {TEACHER_RECORD_FORMAT}, image_size and trained_on, got {sorted(data)}"
        )
    size = image_size(data["image_size"], f"{path}: image_size")
    return {"image_size": size, "trained_on": TrainedOn.from_value(data["trained_on"], f"{path}: trained_on")}


def _checkpoint_dir(checkpoint: str) -> Path:
    """The directory of a local checkpoint, or of an HF id's snapshot in the local cache."""
    from huggingface_hub import snapshot_download
    from huggingface_hub.constants import HF_HUB_CACHE

    path = Path(checkpoint).expanduser()
    if path.is_dir():
        return path
    if path.exists() or checkpoint.startswith((".", "/", "~")):
        raise SemvprError(
            f"teacher checkpoint {path} {'is not a directory' if path.exists() else 'does not exist'}; give "
            f"the folder semvpr.segment saved (<segment run>/teacher), a Hugging Face Mask2Former directory or "
            "a Hub id in the local cache, or set teacher.checkpoint=null to train the embedded teacher"
        )
    try:
        return Path(snapshot_download(checkpoint, local_files_only=True))
    except Exception:  # noqa: BLE001 - a bad id or a missing snapshot: the same advice
        pass
    raise SemvprError(
        f"teacher checkpoint '{checkpoint}' is not available offline (looked in the Hugging Face cache "
        f"{HF_HUB_CACHE}); download it on a machine with internet into HF_HOME (`hf download {checkpoint}`) "
        "and copy that cache here, or set teacher.checkpoint=null to train the embedded teacher"
    )


def _read_json(path: Path) -> dict[str, Any]:
    """A JSON object from a teacher directory (size- and depth-limited; a FIFO or device is never opened)."""
    data = read_json(path, "teacher file")
    if not isinstance(data, dict):
        raise SemvprError(f"{path} is not a JSON object")
    return data


def _mask2former_config(folder: Path) -> Mask2FormerConfig:
    """The checkpoint's Mask2FormerConfig, refused if it asks for any other (or custom) class."""
    path = folder / "config.json"
    if not regular_file(path, "teacher file"):
        if (folder / "teacher" / "config.json").is_file():
            raise SemvprError(
                f"teacher checkpoint {folder} is a semvpr.segment run; name its teacher: {folder / 'teacher'}"
            )
        raise SemvprError(
            f"teacher checkpoint {folder} has no config.json; a teacher directory is the folder semvpr.segment "
            "saved (<segment run>/teacher) or a Hugging Face Mask2Former snapshot"
        )
    data = _read_json(path)
    if data.get("model_type") != "mask2former" or "auto_map" in data:
        raise SemvprError(
            f"{path}: model_type={data.get('model_type')!r}"
            f"{' with auto_map (custom code)' if 'auto_map' in data else ''}; only a plain "
            f"Mask2Former checkpoint (model_type 'mask2former', no custom code) is loaded"
        )
    if data.get("use_pretrained_backbone") or data.get("use_timm_backbone") or data.get("backbone"):
        raise SemvprError(f"{path}: names a separate backbone checkpoint; only self-contained weights are loaded")
    check_config_values(data, path)
    quiet_third_party()
    try:
        return Mask2FormerConfig.from_dict(data)
    except Exception as err:  # noqa: BLE001 - e.g. an unknown backbone model_type
        raise SemvprError(
            f"{path}: not a valid Mask2Former config ({type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''})"
        ) from None


def _normalisation(folder: Path) -> tuple[Sequence[float], Sequence[float]]:
    """Mean and std on [0,1] pixels from ``preprocessor_config.json``; refused if it asks for more."""
    path = folder / "preprocessor_config.json"
    if not regular_file(path, "teacher file"):  # absent: HF's Mask2Former default
        return IMAGENET_MEAN, IMAGENET_STD  # (anything else there, a device or a dangling link too, is refused)
    data = _read_json(path)
    kind = data.get("image_processor_type")
    if kind not in PROCESSOR_TYPES or "auto_map" in data:
        raise SemvprError(f"{path}: image_processor_type={kind!r}; only {list(PROCESSOR_TYPES)} are read")
    for key in ("do_rescale", "do_normalize"):
        if not isinstance(data.get(key, True), bool):
            raise SemvprError(f"{path}: {key}={data[key]!r}: expected true or false")
    factor = data.get("rescale_factor", 1 / 255)
    if data.get("do_rescale", True) and not (float32_number(factor) and math.isclose(factor, 1 / 255)):
        raise SemvprError(f"{path}: rescale_factor={factor!r}; only 1/255 is supported")
    if not data.get("do_normalize", True):
        return (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    mean, std = data.get("image_mean", IMAGENET_MEAN), data.get("image_std", IMAGENET_STD)
    for name, value in (("image_mean", mean), ("image_std", std)):
        # Used in float32: (x - mean) / std must stay finite there (1e308 is finite in float64 only).
        ok = isinstance(value, list | tuple) and len(value) == 3 and all(float32_number(v) for v in value)
        if ok and name == "image_std":
            with np.errstate(over="ignore", divide="ignore"):
                ok = all(v > 0 and np.isfinite(np.float32(1.0) / np.float32(v)) for v in value)
        if not ok:
            raise SemvprError(
                f"{path}: {name}={value!r} is not three numbers finite in float32"
                f"{' and > 0, whose inverse is too' if name == 'image_std' else ''}"
            )
    return tuple(float(v) for v in mean), tuple(float(v) for v in std)


def file_hash(path: Path, length: int = 16) -> str:
    """SHA-256 of a file's bytes (read in 8 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(8 << 20):
            digest.update(block)
    return digest.hexdigest()[:length]


def espnetv2_teacher(spec: TeacherSpec) -> Teacher:
    """ESPNetv2 from its authors' Cityscapes file (``teacher=espnetv2 teacher.checkpoint=FILE``), seeing images
    as the authors' test script does: resized to the inference size (1024x512) bilinearly with antialiasing,
    ImageNet's mean and std; ``predict_batch_size`` images per pass, whatever batch a caller gives."""
    if not spec.checkpoint:
        raise SemvprError(
            "teacher=espnetv2 needs teacher.checkpoint=FILE: an ESPNetv2 Cityscapes segmentation file of its "
            "authors (espnetv2_s_2.0_city_1024x512.pth)"
        )
    path = Path(str(spec.checkpoint)).expanduser()
    kwargs = teacher_options(spec)
    kwargs["id2label"] = dict(enumerate(CITYSCAPES_CHANNELS))
    teacher = Teacher(load_espnetv2(path), image_mean=IMAGENET_MEAN, image_std=IMAGENET_STD, antialias=True, **kwargs)
    teacher.chunk = spec.predict_batch_size
    teacher.source_hash = file_hash(path)
    teacher.trained_on = TrainedOn(f"cityscapes ({path.name})", "real")
    size = list(teacher.inference_size) if teacher.inference_size is not None else None
    teacher.teacher_key = f"espnetv2-{config_hash([teacher.source_hash, size])}"
    return teacher


def teacher_architecture(spec: TeacherSpec) -> Teacher:
    """The teacher this spec describes: ESPNetv2 from its authors' file, a pretrained Mask2Former checkpoint,
    or the embedded Mask2Former untrained."""
    if spec.name == "espnetv2":
        return espnetv2_teacher(spec)
    if spec.checkpoint:
        teacher = load_pretrained(str(spec.checkpoint), **teacher_options(spec))
        # Keyed by content, not by name: a directory whose weights changed is another teacher.
        inference_size = list(teacher.inference_size) if teacher.inference_size is not None else None
        teacher.teacher_key = f"pretrained-{config_hash([teacher.source_hash, inference_size])}"
        return teacher
    return embedded_teacher(spec)

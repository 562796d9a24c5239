"""A checkpoint is data: what it records about the model, and how eval rebuilds a config from it.

Researchers exchange checkpoints, so nothing read from one is ever run. ``torch.load`` uses
``weights_only=True``, and the model is never rebuilt by instantiating ``_target_``s stored in the
file: a checkpoint records *choices* (the config group options, e.g. ``backbone=vgg16``,
``aggregator=sral``, ``mask=student``) and plain hyper-parameter values. Eval loads the project's own group files for
those choices (which alone supply every ``_target_``), and the train config's own ``model`` node for the
model's structure (clusters, whitening, ...), and checks each stored value against them:
known keys only, the same kind of value, no interpolations, no keys starting with ``_``. Anything
else is refused with one line naming the key, before anything is built or written. A recorded
value that names a file or directory to read (``PATH_KEYS``) may be a Hugging Face id, never a
local path, unless the eval invocation names that same path itself.

A checkpoint whose model has a mask also records where its segmenter was trained (``segmenter``: a
:class:`~semvpr.core.provenance.TrainedOn`), so that an evaluation on another kind of images can say
so; checkpoints written before that record have none and read as before.

Resuming training reads Lightning's callback state from the checkpoint too: :class:`RunCheckpoint`
drops any path in it that lies outside the run's checkpoint directory, so a tampered or foreign
``last.ckpt`` can never make Lightning read or delete another file. Checkpoints are written by
:class:`RunCheckpointIO`: staged beside their final name (``core.io.atomic_file``), never in ``$TMPDIR``,
so a run killed mid-save leaves nothing outside its run directory.

Checkpoints written before the aggregator and the mask were groups of their own record a ``filter``
choice (SRAL + student for ``unet``, ...); they are read as the aggregator and mask that the
project's filter preset selects, with the filter's recorded ``weights``. Checkpoints of format 2 recorded
the training protocol and the model's structure together in a ``model`` group; the structure is read,
the protocol (which eval never needs) is left out.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import ModelCheckpoint
from omegaconf import DictConfig, OmegaConf

from semvpr.core.errors import SemvprError
from semvpr.core.io import CONF_DIR, atomic_file
from semvpr.core.provenance import TrainedOn

FORMAT = 3
#: Older formats read here: 2 recorded the training protocol in a ``model`` group (``model=netvlad``).
READABLE_FORMATS = (2, FORMAT)
CONF = Path(CONF_DIR)
#: Config groups that define the model; each group file names itself in its ``name`` key.
GROUPS = ("backbone", "aggregator", "mask", "teacher", "student")
#: Plain nodes of the train config that define the model (checked against the invocation's own).
NODES = ("model",)
#: Settings a checkpoint records now, with the value a run that did not record them ran with.
BEFORE_RECORDED = {"teacher": {"share_trunk": False}}
_CHOICE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_\-]*$")
#: Recorded (group, key)s whose value names something to read: a Hugging Face id or null.
PATH_KEYS = (("teacher", "checkpoint"), ("student", "checkpoint"))
_HF_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]*/[A-Za-z0-9][A-Za-z0-9_.\-]*$")


def record_of(cfg: DictConfig, segmenter: TrainedOn | None = None) -> dict[str, Any]:
    """What a checkpoint records about a run's model: format, group choices, plain values, seed, and the data
    the mask's segmenter was trained on (``segmenter``; absent without one)."""
    config: dict[str, Any] = {}
    for group in (*GROUPS, *NODES):
        node = OmegaConf.to_container(cfg[group], resolve=True)
        assert isinstance(node, dict)
        config[group] = _plain(node)
    record = {
        "format": FORMAT,
        "choices": {g: str(cfg[g].name) for g in GROUPS},
        "config": config,
        "seed": int(cfg.seed),
    }
    if segmenter is not None:
        record["segmenter"] = segmenter.as_dict()
    return record


def _plain(node: Any) -> Any:
    """The node without ``_``-keys (targets come from the project's configs, never from a file)."""
    if isinstance(node, dict):
        return {k: _plain(v) for k, v in node.items() if not str(k).startswith("_")}
    if isinstance(node, list):
        return [_plain(v) for v in node]
    return node


#: What a weights-only read lets a file hold besides tensors and plain containers: numpy scalars (the
#: recall values pytorch-NetVlad's ``checkpoint.pth.tar`` stores beside its weights), rebuilt from bytes.
#: A scalar pickled by numpy 1 names ``numpy.core.multiarray.scalar``, by numpy 2 ``numpy._core...``.
_SAFE_NUMPY = (
    *((np._core.multiarray.scalar, f"{module}.multiarray.scalar") for module in ("numpy.core", "numpy._core")),
    np.dtype,
    *(type(np.dtype(t)) for t in (np.float64, np.float32, np.int64, np.int32, np.bool_)),
)
_UNSUPPORTED = re.compile(r"Unsupported global: GLOBAL (\S+)")


def read_weights(path: str | Path, what: str = "checkpoint") -> Any:
    """A torch file's contents read weights-only (tensors, plain values and numpy scalars; nothing in it
    runs). A file that pickles any other object is refused in one line naming that object."""
    path = Path(path)
    if not path.is_file():
        hint = " (a run writes <run dir>/checkpoints/tested.ckpt)" if what == "checkpoint" else ""
        raise SemvprError(f"{what} {path} not found{hint}")
    try:
        with torch.serialization.safe_globals(list(_SAFE_NUMPY)):
            return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unreadable file gets the same one line
        pickled = _UNSUPPORTED.search(str(err))
        if pickled is not None:
            raise SemvprError(
                f"{what} {path} is refused: it pickles an object ({pickled.group(1)}), and only weights are "
                "read from a file (nothing in it is run)"
            ) from None
        detail = (str(err).splitlines() or [""])[0]
        raise SemvprError(
            f"{path} is not a readable {what} ({type(err).__name__}{': ' + detail if detail else ''})"
        ) from None


def is_semvpr_checkpoint(contents: Any) -> bool:
    """Whether a file's contents carry a semvpr model record (of any format)."""
    record = contents.get("hyper_parameters") if isinstance(contents, dict) else None
    return isinstance(record, dict) and ("format" in record or "config" in record)


def read_checkpoint(path: str | Path, contents: Any = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The state dict and the model record of a semvpr checkpoint (weights-only load; ``contents``: the
    file's, where already read)."""
    path = Path(path)
    ckpt = read_weights(path) if contents is None else contents
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict):
        raise SemvprError(f"{path} is not a semvpr checkpoint (no state_dict)")
    broken = next(
        (
            k
            for k, v in ckpt["state_dict"].items()
            if not isinstance(v, torch.Tensor) or (v.is_floating_point() and not torch.isfinite(v).all())
        ),
        None,
    )
    if broken is not None:
        raise SemvprError(f"{path}: weight {broken!r} is not a tensor of finite numbers; the checkpoint is damaged")
    record = ckpt.get("hyper_parameters")
    if not isinstance(record, dict) or record.get("format") not in READABLE_FORMATS:
        if isinstance(record, dict) and "config" in record and "format" not in record:
            raise SemvprError(
                f"{path} was written by an older semvpr (checkpoint format 1: it stores Hydra "
                "_target_s, and its VGG16 features were cut after conv5_3's ReLU); it cannot be "
                "loaded safely or faithfully: retrain it with this version"
            )
        raise SemvprError(f"{path} is not a semvpr checkpoint of format {FORMAT} (no model record)")
    return ckpt["state_dict"], record


def model_config(
    record: dict[str, Any], base: DictConfig, where: str = "checkpoint", check_paths: bool = True
) -> DictConfig:
    """``base`` (the invocation's config: data, paths, ...) with the recorded model, validated.

    Each group is replaced by the project's own file for the recorded choice; the recorded values
    are then checked against that file (see the module docstring) and applied. ``check_paths=False``
    leaves the recorded paths to the caller (:func:`check_recorded_paths`), which replaces them when
    the invocation names another mask source.
    """
    choices, config = record.get("choices"), record.get("config")
    if not isinstance(choices, dict) or not isinstance(config, dict):
        raise SemvprError(f"{where}: model record lacks 'choices' / 'config'")
    if "filter" in choices and "aggregator" not in choices:
        choices, config = _from_filter(choices, config, where)
    if record.get("format") == 2:
        choices, config = _from_model_group(choices, config, base)
    unknown = sorted(set(choices) - set(GROUPS)) or sorted(set(config) - set(GROUPS) - set(NODES))
    if unknown:
        raise SemvprError(f"{where}: '{unknown[0]}' is not a model config group ({', '.join(GROUPS)})")
    cfg = base.copy()
    for group in GROUPS:
        choice = choices.get(group)
        options = sorted(p.stem for p in (CONF / group).glob("*.yaml"))
        if not isinstance(choice, str) or not _CHOICE.match(choice) or choice not in options:
            raise SemvprError(
                f"{where}: choices.{group}={choice!r} is not one of the project's {group} configs {options}"
            )
        cfg[group] = OmegaConf.load(CONF / group / f"{choice}.yaml")
    seed = record.get("seed")
    if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed < 2**32:
        raise SemvprError(f"{where}: seed={seed!r} is not a whole number from 0 to 2**32-1")
    cfg.seed = seed
    for group in (*GROUPS, *NODES):
        stored = config.get(group, {})
        schema = OmegaConf.to_container(cfg[group], resolve=True)
        _check(stored, schema, f"{where}: {group}")
        cfg[group] = OmegaConf.merge(cfg[group], stored)
        for key, value in BEFORE_RECORDED.get(group, {}).items():
            if isinstance(stored, dict) and key not in stored and key in cfg[group]:
                cfg[group][key] = value
    segmenter_of(record, where)
    if check_paths:
        check_recorded_paths(record, base, where)
    return cfg


def check_recorded_paths(record: dict[str, Any], base: DictConfig, where: str = "checkpoint") -> None:
    """Refuse a recorded value naming a local path (``PATH_KEYS``) that the invocation does not name itself."""
    config = record.get("config") or {}
    for group, key in PATH_KEYS:
        stored = config.get(group, {}).get(key) if isinstance(config.get(group), dict) else None
        _check_path_value(stored, base[group].get(key), f"{where}: {group}.{key}")


def segmenter_of(record: dict[str, Any], where: str = "checkpoint") -> TrainedOn | None:
    """The data the checkpoint's mask segmenter was trained on; None where the record does not say."""
    if "segmenter" not in record:
        return None
    return TrainedOn.from_value(record["segmenter"], f"{where}: segmenter")


def _from_filter(choices: dict[str, Any], config: dict[str, Any], where: str) -> tuple[dict, dict]:
    """A record naming a ``filter`` preset, as the aggregator and mask choices the preset selects."""
    choices, config = dict(choices), dict(config)
    choice = choices.pop("filter")
    stored = config.pop("filter", {})
    options = sorted(p.stem for p in (CONF / "filter").glob("*.yaml"))
    if not isinstance(choice, str) or choice not in options or not isinstance(stored, dict):
        raise SemvprError(f"{where}: choices.filter={choice!r} is not one of the project's filter presets {options}")
    for entry in OmegaConf.load(CONF / "filter" / f"{choice}.yaml").get("defaults", []):
        for key, value in entry.items():  # "override /aggregator": "sral"
            choices[key.split("/")[-1]] = value
    config["mask"] = {"weights": stored.get("weights", "binary")}
    return choices, config


def _from_model_group(choices: dict[str, Any], config: dict[str, Any], base: DictConfig) -> tuple[dict, dict]:
    """A format-2 record: its ``model`` group held the model's structure and the training protocol; the
    structure is read into the ``model`` node, the protocol (training only) is left out."""
    choices = {k: v for k, v in choices.items() if k != "model"}
    config = dict(config)
    stored = config.get("model")
    if isinstance(stored, dict):
        config["model"] = _known_part(stored, OmegaConf.to_container(base.model, resolve=True))
    return choices, config


def _known_part(stored: dict[str, Any], schema: Any) -> dict[str, Any]:
    """The keys of ``stored`` (recursively) that ``schema`` has."""
    if not isinstance(schema, dict):
        return {}
    return {k: _known_part(v, schema[k]) if isinstance(v, dict) else v for k, v in stored.items() if k in schema}


def _check_path_value(stored: Any, given: Any, path: str) -> None:
    """A stored value naming something to read must be a Hugging Face id, or the invocation's own."""
    if stored is None or stored == given:
        return
    text = str(stored)
    if not _HF_ID.match(text) or ".." in text.split("/") or Path(text).expanduser().exists():
        raise SemvprError(
            f"{path}={text!r} names a local path; a checkpoint's stored choices never do "
            f"(pass {path.rsplit(': ', 1)[-1]}={text} yourself to use that directory)"
        )


def _check(stored: Any, schema: Any, path: str) -> None:
    """Refuse a stored value that the project's config could not have produced."""
    check_values(stored, schema, path, source="a checkpoint")


def check_values(stored: Any, schema: Any, path: str, *, source: str, project_values: Any = None) -> None:
    """Refuse a stored value (a checkpoint's record, a resumed run's config) that the project's config
    could not have produced: only keys of ``schema`` (an empty mapping there takes keys of the user's
    own: ``data.render: {}``), values of the same kind, no ``_`` keys and no ``${...}``, unless
    ``project_values`` (the project's config at the same place, unresolved) holds exactly the same
    entry: a resumed run's record carries the ``_target_``s and interpolations of the files it was
    composed from, which add nothing. ``source`` names what was read, for the one-line refusal; ``path``
    prefixes every key named (a path ending in ": " is a heading, not a key)."""
    if isinstance(stored, dict):
        if not isinstance(schema, dict):
            raise SemvprError(f"{path} is a mapping where the project's config has {schema!r}")
        project = project_values if isinstance(project_values, dict) else {}
        for key, value in stored.items():
            if isinstance(key, str) and key in project and project[key] == value and _project_only(key, value):
                continue  # the project's own _target_ / interpolation, unchanged
            if not isinstance(key, str) or key.startswith("_"):
                raise SemvprError(
                    f"{_join(path, key)} is refused: keys such as _target_ are never read from {source} "
                    "(the project's config files supply them)"
                )
            if key not in schema:
                if schema:
                    raise SemvprError(f"{_join(path, key)} is not a key of the project's config")
                if isinstance(value, (dict, list)):
                    raise SemvprError(f"{_join(path, key)} is not a plain value")
                check_values(value, None, f"{_join(path, key)}", source=source)
                continue
            check_values(value, schema[key], f"{_join(path, key)}", source=source, project_values=project.get(key))
    elif isinstance(stored, list):
        if schema is not None and not isinstance(schema, list):
            raise SemvprError(f"{path} is a list where the project's config has {schema!r}")
        for i, value in enumerate(stored):
            if isinstance(value, (dict, list)):
                raise SemvprError(f"{path}[{i}] is not a plain value")
            check_values(value, None, f"{path}[{i}]", source=source)
    else:
        if isinstance(stored, str) and "${" in stored:
            raise SemvprError(f"{path}={stored!r} is refused: interpolations are never read from {source}")
        derived = isinstance(project_values, str) and "${" in project_values
        if not derived and not _same_kind(stored, schema):
            raise SemvprError(f"{path}={stored!r} has the wrong type (the project's config has {schema!r})")


def _join(path: str, key: object) -> str:
    """``path.key``, or ``path key`` after a heading (``"resuming <run>: "``)."""
    return f"{path}{key}" if path.endswith(": ") else f"{path}.{key}"


def _project_only(key: str, value: Any) -> bool:
    """Whether an entry is one only the project's files may supply (a ``_`` key, or text with ``${``)."""
    if key.startswith("_"):
        return True
    if isinstance(value, str):
        return "${" in value
    if isinstance(value, dict):
        return any(_project_only(str(k), v) for k, v in value.items())
    if isinstance(value, list):
        return any(isinstance(v, str) and "${" in v for v in value)
    return False


def _same_kind(value: Any, schema: Any) -> bool:
    """Whether a plain stored value may replace the config's value (null accepts any plain value)."""
    if value is not None and not isinstance(value, (bool, int, float, str)):
        return False
    if schema is None or value is None:
        return True
    if schema == "auto":  # a setting the project leaves to semvpr (threads, device) takes a number or a word
        return isinstance(value, (int, str)) and not isinstance(value, bool)
    if isinstance(schema, bool) or isinstance(value, bool):
        return isinstance(schema, bool) and isinstance(value, bool)
    if isinstance(schema, float):
        return isinstance(value, (int, float))
    return type(value) is type(schema)


class RunCheckpoint(ModelCheckpoint):
    """Lightning's ModelCheckpoint, restoring from a checkpoint only paths inside its own ``dirpath``.

    On resume Lightning restores ``best_model_path`` etc. from the file and later deletes or loads
    those files; a path elsewhere (a tampered ``last.ckpt``, another run's checkpoint) is dropped
    here, with the score that went with it.
    """

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(confine_callback_state(state_dict, Path(self.dirpath or ".")))


def confine_callback_state(state: dict[str, Any], dirpath: Path) -> dict[str, Any]:
    """ModelCheckpoint state with every file outside ``dirpath`` forgotten."""
    root = dirpath.resolve()

    def inside(value: Any) -> bool:
        return isinstance(value, str) and bool(value) and Path(value).resolve().is_relative_to(root)

    state = dict(state)
    for key in ("best_model_path", "kth_best_model_path", "last_model_path"):
        if key in state and not inside(state[key]):
            state[key] = ""
    if not state.get("best_model_path"):
        state["best_model_score"] = None
    if isinstance(state.get("best_k_models"), dict):
        state["best_k_models"] = {k: v for k, v in state["best_k_models"].items() if inside(k)}
    return state


class RunCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint writer, staging each file beside its target (``core.io.atomic_file``: a fresh
    hidden name in the same folder, renamed when complete) where Lightning's own stages it in ``$TMPDIR``
    (fsspec's transaction), outside the run directory."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__}.save_checkpoint takes no storage_options, got {storage_options!r}")
        with atomic_file(Path(path)) as handle:
            torch.save(checkpoint, handle)

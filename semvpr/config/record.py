"""A run's model as a checkpoint records it, and the config eval rebuilds from that record.

A checkpoint records *choices* (the config group options, e.g. ``backbone=vgg16``, ``aggregator=sral``,
``mask=student``) and plain hyper-parameter values (``semvpr.core.checkpoint`` reads the file as data).
Eval loads the project's own group files for those choices (which alone supply every ``_target_``), and the
train config's own ``model`` node for the model's structure (clusters, whitening, ...), and checks each
stored value against them (``core.checkpoint.check_values``: known keys only, the same kind of value, no
interpolations, no keys starting with ``_``). Anything else is refused with one line naming the key, before
anything is built or written. A recorded value that names a file or directory to read (``PATH_KEYS``) may
be a Hugging Face id, never a local path, unless the eval invocation names that same path itself.

Checkpoints written before the aggregator and the mask were groups of their own record a ``filter``
choice (SRAL + student for ``unet``, ...); they are read as the aggregator and mask that the
project's filter preset selects, with the filter's recorded ``weights``. Checkpoints of format 2 recorded
the training protocol and the model's structure together in a ``model`` group; the structure is read,
the protocol (which eval never needs) is left out. Checkpoints of formats 2 and 3 recorded the constructor's
values of the backbone, the aggregator and the mask source in a ``module`` node of each group; they are read
as the group's own values, where the project's files hold them now.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from semvpr.config.schema import RunSettings, typed
from semvpr.core.checkpoint import FORMAT, check_values, segmenter_of
from semvpr.core.errors import SemvprError
from semvpr.core.io import CONF_DIR

CONF = Path(CONF_DIR)
#: Config groups that define the model; each group file names itself in its ``name`` key.
GROUPS = ("backbone", "aggregator", "mask", "teacher", "student")
#: Plain nodes of the train config that define the model (checked against the invocation's own).
NODES = ("model",)
#: Recorded settings that older checkpoints lack, with the value the runs that wrote them used.
BEFORE_RECORDED = {"teacher": {"share_trunk": False}}
_CHOICE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_\-]*$")
#: Recorded (group, key)s whose value names something to read: a Hugging Face id or null.
PATH_KEYS = (("teacher", "checkpoint"), ("student", "checkpoint"))
_HF_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]*/[A-Za-z0-9][A-Za-z0-9_.\-]*$")


def record_of(cfg: DictConfig) -> dict[str, Any]:
    """What a checkpoint records about a run's model: format, group choices, plain values and seed (the
    retriever's builder adds the grid a fixed-grid aggregator was built for and the data the mask's segmenter
    was trained on: ``config.build.build_retriever``)."""
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
    return record


def _plain(node: Any) -> Any:
    """The node without ``_``-keys (targets come from the project's configs, never from a file)."""
    if isinstance(node, dict):
        return {k: _plain(v) for k, v in node.items() if not str(k).startswith("_")}
    if isinstance(node, list):
        return [_plain(v) for v in node]
    return node


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
    if record.get("format") in (2, 3):
        config = _from_module_nodes(config)
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
    try:
        cfg.seed = typed(RunSettings, {"seed": record.get("seed")}).seed
    except SemvprError as err:
        raise SemvprError(f"{where}: {err}") from None
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


def _from_module_nodes(config: dict[str, Any]) -> dict[str, Any]:
    """A record of format 2 or 3: each component group's ``module`` node (its constructor's values; a backbone's
    repeated the group's own) is read as the group's values, which the project's files now hold beside the class."""
    config = dict(config)
    for group in ("backbone", "aggregator", "mask"):
        stored = config.get(group)
        if isinstance(stored, dict) and "module" in stored:
            stored = dict(stored)
            module = stored.pop("module")
            if isinstance(module, dict):
                stored.update(module)
            elif module is not None:
                stored["module"] = module  # refused by the value check, as any value the files cannot hold
            config[group] = stored
    return config


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

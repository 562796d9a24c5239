"""``check_config``: the one place a run's settings are checked, first thing in every command, before
anything is read or written, so a bad value is one line naming its key instead of a late traceback."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from semvpr.config.components import (
    COMPONENTS,
    component_class,
    constructor_values,
    group_settings,
    options,
    recipe_of,
    refuse_mistyped_values,
)
from semvpr.config.schema import (
    SIZE_MAX,
    DataNode,
    EvalSettings,
    Features,
    GsvRecipe,
    Model,
    OptimizerNode,
    OtherPlaceSet,
    RunSettings,
    SegmentSettings,
    SegNode,
    TrainerSettings,
    TripletRecipe,
    typed,
)
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import CONF_DIR, check_dir_path, check_path_text
from semvpr.core.patterns import bounded_regex
from semvpr.core.precision import lightning_precision
from semvpr.core.spec import number, whole_number
from semvpr.core.threads import parse_setting
from semvpr.retrieval.controls import REMOVED_CLASSES


def _leaves(node: object, prefix: str = "") -> set[str]:
    """Dotted keys of a plain mapping's leaves."""
    if not isinstance(node, dict):
        return {prefix.rstrip(".")}
    return set().union(*(_leaves(v, f"{prefix}{k}.") for k, v in node.items())) if node else set()


def _open_nodes(node: object, prefix: str = "") -> set[str]:
    """Dotted keys of the empty mappings of a config: where it leaves room for keys of the user's own
    (``data.render: {}`` takes any SynthCity knob)."""
    if not isinstance(node, dict):
        return set()
    if not node:
        return {prefix.rstrip(".")}
    return set().union(*(_open_nodes(v, f"{prefix}{k}.") for k, v in node.items()))


#: Nodes that take keys the project's files do not list: Lightning Trainer arguments (+trainer.sync_batchnorm=true).
OPEN_NODES = ("trainer",)
#: Command-line flags after which the arguments are not all overrides (the pre-flight then leaves them to Hydra).
_HYDRA_FLAGS = ("-m", "--multirun")


#: Config groups whose files name themselves in ``<group>.name`` (the file's stem).
NAMED_GROUPS = ("data", "backbone", "aggregator", "mask", "filter", "recipe", "teacher", "student", "seg")


def check_overrides(argv: list[str], config_name: str = "train") -> None:
    """Check a command line's overrides before Hydra runs, so that a bad one is one line:

    - one that renames a group's file (``aggregator.name=gem``: the run would be labelled, and its checkpoint
      recorded, as another than it is) names the group choice to make instead;
    - one that names the training protocol as a ``model`` group or ``model.`` setting (it is the
      ``recipe`` group), or a key of recipe=gsv's interpolated optimiser or scheduler, says where it is;
    - one Hydra cannot parse or apply (a typo'd key, a value with unquoted ``,`` or ``"``) is Hydra's
      reason in one line;
    - one that adds a key the project's config does not have (``+model.fooo=1``) is refused: nothing
      would read it, so the run would silently be another than asked;
    - ``hydra.run.dir`` / ``hydra.sweep.dir`` must be a directory semvpr can write as written
      (``core.io.check_dir_path``), checked before Hydra makes it and opens its log there;
    - a key starting with ``_`` (``data.test._target_=builtins.exec``, or inside a mapping value) is
      refused: ``_target_``s come only from the project's config files, a class is chosen by its group;
    - ``-m`` between overrides (Hydra's argument parser takes it only before or after them all) names the
      order that runs.
    """
    recipe = _leaves(OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "recipe" / "triplet.yaml")))
    model = _leaves(OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "train.yaml").model))
    gsv = any(a.partition("=")[0] == "recipe" and "gsv" in a.partition("=")[2].split(",") for a in argv)
    for arg in argv:
        key, sep, value = arg.lstrip("+~").partition("=")
        if key == "model" and sep:
            raise SemvprError(
                f"{arg}: the training protocol is the recipe group now: model=netvlad is recipe=triplet "
                f"({', '.join(options('recipe'))})"
            )
        if key.startswith(("recipe.optimizer.", "recipe.scheduler.")) and gsv:
            group, rest = key.split(".")[1], key.removeprefix("recipe.")
            raise SemvprError(
                f"{arg}: recipe=gsv takes the aggregator's published {group} (an interpolation); override "
                f"aggregator.gsv.{rest}={value}, or recipe.default.{rest}={value} for an aggregator without "
                "a gsv node (GeM, NetVLAD)"
            )
        node = key.removesuffix(".name")
        group = "backbone" if re.fullmatch(r"backbones\.[^.]+", node) else node  # segment's students' trunks
        if sep and key.endswith(".name") and group in NAMED_GROUPS:
            choice = f"{group}@{node}" if group != node else group
            raise SemvprError(
                f"{arg}: {key} is the name of the {group} file chosen (it labels the run and what a checkpoint "
                f"records), not a setting; choose another with {choice}=NAME ({', '.join(options(group))})"
            )
        rest = key.removeprefix("model.")
        if (
            key.startswith("model.")
            and rest not in model
            and any(r == rest or r.startswith(f"{rest}.") for r in recipe)
        ):
            raise SemvprError(f"{arg}: {key} is a setting of the training protocol now: recipe.{rest}={value}")
    for arg in argv:
        _refuse_private_keys(arg)
    args = [a for a in argv if a not in _HYDRA_FLAGS]
    at = next((i for i, a in enumerate(argv) if a in _HYDRA_FLAGS), None)
    if at is not None and 0 < at < len(argv) - 1:  # first or last is what Hydra's argument parser takes
        flag = argv[at]
        raise SemvprError(
            f"{flag} goes before the overrides (Hydra reads those after it as unrecognized arguments): "
            f"python -m semvpr.{config_name} {flag} {' '.join(args)}"
        )
    if any(a.startswith("-") for a in args):
        return  # --cfg, --config-name, ...: Hydra's own modes
    _check_composition(args, config_name, multirun=len(args) < len(argv))


def _refuse_private_keys(arg: str) -> None:
    """Refuse an override (outside ``hydra.``) whose key, or a key of whose mapping value, starts with ``_``
    (``_target_``, ``_partial_``, ``_args_``, ...): only the project's config files name what is built."""
    if arg.startswith("-"):
        return
    key, sep, value = arg.lstrip("+~").partition("=")
    if key == "hydra" or key.startswith(("hydra.", "hydra/")):
        return
    named = next((part for part in re.split(r"[./@]", key) if part.startswith("_")), None)
    if named is None and sep and "_" in value:
        named = _private_key_in(_parsed_value(arg))
    if named is not None:
        raise SemvprError(
            f"{arg}: the key {named} is refused on the command line: _target_ and the other _ keys come only from "
            "the project's config files (choose a class by its group, e.g. aggregator=gem)"
        )


def _parsed_value(arg: str) -> Any:
    """The value of one override as Hydra parses it (None where it does not parse: Hydra says why later)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        (override,) = OverridesParser.create().parse_overrides([arg])
        return override.value()
    except Exception:  # noqa: BLE001 - any parse failure is reported by the composition check
        return None


def _private_key_in(value: Any) -> str | None:
    """The first mapping key starting with ``_`` anywhere in a parsed override value, or None."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            for k, v in item.items():
                if str(k).startswith("_"):
                    return str(k)
                stack.append(v)
        elif isinstance(item, list):
            stack.extend(item)
    return None


def _check_composition(args: list[str], config_name: str, multirun: bool) -> None:
    """Parse the overrides as Hydra does, check the run or sweep dir, compose the config with them and
    refuse keys the project's config has no room for (see :func:`check_overrides`). In a sweep, a key
    is known if the config of one of the swept group choices has it (``data=a,b ++data.set=x``)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    try:
        parsed = parser.parse_overrides(args)
    except Exception as err:  # noqa: BLE001 - Hydra's parse errors: one line with its reason
        raise SemvprError(_parse_failure(parser, args, err)) from None
    for override in parsed:
        if override.key_or_group in ("hydra.run.dir", "hydra.sweep.dir") and not override.is_sweep_override():
            value = override.value()
            if isinstance(value, str) and "${" not in value:
                check_dir_path(value, override.key_or_group)

    def is_group(override: Any) -> bool:
        return (Path(CONF_DIR) / override.key_or_group.split("@")[0]).is_dir()

    launcher = [o for o in parsed if o.key_or_group.startswith(("hydra.launcher", "hydra/launcher"))]
    if launcher:
        _check_launcher([o.input_line for o in launcher], config_name)
    ours = [o for o in parsed if o.key_or_group != "hydra" and not o.key_or_group.startswith(("hydra.", "hydra/"))]
    kept = [o.input_line for o in ours if not (multirun and o.is_sweep_override())]
    variants: list[list[str]] = []
    for override in (o for o in ours if multirun and o.is_sweep_override()):
        if not is_group(override):
            continue  # a swept value: the key is checked by Hydra in each job
        try:
            values = list(override.sweep_string_iterator())
        except Exception:  # noqa: BLE001 - a glob or range over a group: left to Hydra
            return
        key = override.input_line.partition("=")[0]
        variants += [[f"{key}={value}"] for value in values]
    groups = [o.input_line for o in ours if is_group(o) and not (multirun and o.is_sweep_override())]
    given: set[str] = set()
    known: set[str] = set()
    room: set[str] = set(OPEN_NODES)
    failures: list[str] = []
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        for variant in variants or [[]]:
            try:
                cfg = compose(config_name=config_name, overrides=[*kept, *variant])
                plain = OmegaConf.to_container(compose(config_name=config_name, overrides=[*groups, *variant]))
            except Exception as err:  # noqa: BLE001 - Hydra's composition errors: one line with its reason
                failures.append(_first_line(err))
                continue
            given |= _leaves(OmegaConf.to_container(cfg, resolve=False))
            known |= _leaves(plain)
            room |= _open_nodes(plain)
    # In a sweep over groups, a choice the overrides do not fit fails its own job (Hydra says why there).
    if failures and len(failures) == len(variants or [[]]):
        unknown = re.match(r"Could not override '([^']+)'", failures[0])
        if unknown:  # Hydra's hint (append it with +) would only meet the refusal below
            raise SemvprError(_unknown(unknown.group(1)))
        raise SemvprError(f"cannot apply the overrides: {failures[0]}")
    for key in sorted(given - known):
        if not any(key == r or key.startswith(f"{r}.") for r in room):
            raise SemvprError(_unknown(key))


def _check_launcher(overrides: list[str], config_name: str) -> None:
    """The launcher the command line chooses, with the settings it gives it: a setting the launcher does not
    have (``hydra.launcher.n_jobs`` under ``hydra/launcher=basic``), or a launcher whose plugin is not
    installed, is one line naming the launcher."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        try:
            launcher = compose(config_name=config_name, overrides=overrides, return_hydra_config=True).hydra.launcher
        except Exception as err:  # noqa: BLE001 - told apart below: an unknown launcher, setting or value
            failure = err
        else:
            if launcher.get("n_jobs") == 0:  # joblib's ValueError once the sweep has started
                raise SemvprError(
                    "hydra.launcher.n_jobs=0 must be a whole number other than 0 (jobs at once; -1: one per core)"
                )
            return
        chosen = [o for o in overrides if o.startswith("hydra/launcher=")]
        try:
            base = compose(config_name=config_name, overrides=chosen, return_hydra_config=True)
        except Exception as err:  # noqa: BLE001 - an unknown launcher: Hydra lists the installed ones
            name = chosen[-1].partition("=")[2]
            hint = "; pip install -e '.[cluster]' adds the submitit launchers" if "submitit" in name else ""
            found = re.search(r"Available options in 'hydra/launcher':\s*(.*?)\s*Config search path", str(err), re.S)
            known = f" (installed: {' '.join(found.group(1).split())})" if found else f": {_first_line(err)}"
            raise SemvprError(f"{chosen[-1]}: no such launcher here{known}{hint}") from None
    unknown = re.search(r"Could not override '([^']+)'", str(failure))
    name = base.hydra.runtime.choices.get("hydra/launcher")
    cause: BaseException | None = failure
    while unknown is None and cause is not None:  # a setting it has, given a value of another type
        if type(cause).__name__ == "ValidationError":
            key = re.search(r"full_key: (\S+)", str(cause))
            given = next((o for o in overrides if key and o.lstrip("+~").startswith(f"{key.group(1)}=")), None)
            raise SemvprError(f"{given or name}: {str(cause).strip().splitlines()[0]}") from None
        cause = cause.__cause__ or cause.__context__
    settings = ", ".join(k for k in base.hydra.launcher if k != "_target_") or "none"
    what = unknown.group(1) if unknown else _first_line(failure)
    raise SemvprError(
        f"{what} is not a setting of the {name} launcher (hydra/launcher={name}); its settings: {settings}"
    )


def _unknown(key: str) -> str:
    return (
        f"{key} is not a setting of the project's config (a typo?); nothing would read it, "
        f"so the run would not be the one asked for"
    )


def _parse_failure(parser: Any, args: list[str], err: BaseException) -> str:
    """Hydra's reason a command line does not parse, naming the override at fault; where its value holds
    ``=`` or ``,`` (a path through a sweep job's folder, ``filter=unet,seed=0``), the quoted form that parses."""
    for arg in args:
        try:
            parser.parse_overrides([arg])
        except Exception as one:  # noqa: BLE001 - the first override that fails alone
            key, _, value = arg.partition("=")
            hint = ""
            if any(c in value for c in "=,") and "'" not in value:
                hint = (
                    f"; a value holding '=' or ',' (a sweep job's folder, e.g. filter=unet,seed=0) is quoted "
                    f"inside the override: \"{key}='{value}'\""
                )
            return f"cannot parse the override {arg!r}: {_first_line(one)}{hint}"
    return f"cannot parse the overrides: {_first_line(err)}"


def _first_line(err: BaseException) -> str:
    """An exception's reason in one line (Hydra's messages run over several)."""
    cause = err
    while cause.__cause__ is not None and not str(cause).strip():
        cause = cause.__cause__
    lines = [ln.strip() for ln in str(cause).splitlines() if ln.strip() and not ln.strip().startswith("See http")]
    return " ".join(lines)[:300] or type(err).__name__


@exit_on_user_error
def check_overrides_or_exit(argv: list[str], config_name: str = "train") -> None:
    """:func:`check_overrides` as a command's first step: one line and exit code 2."""
    check_overrides(argv, config_name)


def check_config(cfg: DictConfig, run_dir: Path | None = None) -> None:
    """Reject config values that would fail deep inside a run with a cryptic error (or none at all).

    One function for every command's config: the retrieval settings where the config has them (train,
    eval, localize), the segmentation set's where it has one (segment); ``run_dir``, the directory the
    command writes into, must be usable as written (``core.io.check_dir_path``).
    """
    parse_setting(cfg.get("threads", "auto"))
    check_dir_path(str(cfg.paths.cache_dir), "paths.cache_dir", writable=False)
    if run_dir is not None:
        check_dir_path(str(run_dir), "the run dir (hydra.run.dir)")
    for key in PATH_KEYS:
        _check_path_setting(OmegaConf.select(cfg, key, default=None, throw_on_missing=False), key)
    if "init" in cfg:
        typed(OtherPlaceSet, cfg.init, "init")
    trunks = {"backbone": cfg.backbone} if "backbone" in cfg else {}  # segment's students' trunks: backbones.*
    trunks |= {f"backbones.{name}": node for name, node in (cfg.get("backbones") or {}).items()}
    for where, node in trunks.items():
        weights = node.get("weights", "none")
        if weights is None:
            raise SemvprError(f"{where}.weights=null: give imagenet, none (a random-init trunk) or a weight file")
        _check_path_setting(weights, f"{where}.weights")
    if "ckpt_format" in cfg:
        typed(EvalSettings, cfg, part=True)
    pattern = OmegaConf.select(cfg, "data.frame_pattern", default=None, throw_on_missing=False)
    if pattern is not None:
        bounded_regex(pattern, "data.frame_pattern")
    if "model" in cfg:
        _check_retrieval(cfg)
    if "seg" in cfg:
        _check_segmentation(cfg)
    # After the keys they interpolate (teacher.image_size is ${data.image_size}): the error names the source.
    _check_semantic_settings(cfg)
    _check_finite(cfg)


def _check_finite(cfg: DictConfig) -> None:
    """No setting is a non-finite number (``recipe.loss.epsilon=nan`` would mine nothing and train nothing,
    silently); the settings with their own checks above say so in their own words first."""
    try:
        values = OmegaConf.to_container(cfg, resolve=True)
    except Exception:  # noqa: BLE001 - an unresolvable value is reported where it is read
        values = OmegaConf.to_container(cfg, resolve=False)
    stack: list[tuple[Any, str]] = [(values, "")]
    while stack:
        item, key = stack.pop()
        if isinstance(item, dict):
            stack.extend((v, f"{key}.{k}" if key else str(k)) for k, v in item.items() if k != "hydra")
        elif isinstance(item, list):
            stack.extend((v, f"{key}[{i}]") for i, v in enumerate(item))
        elif isinstance(item, float) and not math.isfinite(item):
            raise SemvprError(f"{key}={item} is not a finite number")


def _check_semantic_settings(cfg: DictConfig) -> None:
    """The teacher's and the student's typed settings, where the config has them: a value of the wrong
    kind (``student.flip=maybe``) is one line before any work, not a truthy surprise after it."""
    from semvpr.config.plan import student_spec, teacher_spec

    if cfg.get("teacher") is not None:
        teacher_spec(cfg)
    if cfg.get("student") is not None:
        student_spec(cfg)


#: Settings that name a file or folder to read; a NUL or an over-long name is refused before any reader.
PATH_KEYS = (
    "data.root",
    "data.seg_root",
    "data.gt_dir",
    "data.npz",
    "data.db_list",
    "data.q_list",
    "ckpt",
    "ckpt_path",
    "queries",
    "teacher.checkpoint",
    "student.checkpoint",
    "init.root",
    "seg.root",
)


def _check_path_setting(value: object, key: str) -> None:
    """A setting of :data:`PATH_KEYS`: unset (null), or a name the file system can hold; a number or a list
    (``data.root=2024``, ``data.root=[a,b]``: Hydra's types) or an empty name is one line."""
    if value is None:
        return
    if OmegaConf.is_config(value) or isinstance(value, (list, dict)):
        raise SemvprError(f"{key}={_shown(value)!r} is not a path: name one file or folder")
    if not isinstance(value, str):
        written = str(value).lower() if isinstance(value, bool) else str(value)
        raise SemvprError(f"{key}={written} is not a path; a folder or file of that name is quoted: {key}='{written}'")
    if not value:
        raise SemvprError(f"{key}='' names no file or folder")
    check_path_text(value, key)


def check_model(cfg: DictConfig, where: str = "") -> None:
    """The model's structure (its components' classes and values, the ``model`` node and the aggregator's
    sizes): what a checkpoint records, so eval checks it again on the config merged from the checkpoint
    (``where`` says so)."""
    prefix = f"{where}: " if where else ""
    try:
        for group in COMPONENTS:
            component_class(cfg, group)
        typed(Model, cfg.model, "model")
        group_settings(cfg, "mask")
        group_settings(cfg, "aggregator")
        values = constructor_values(cfg.aggregator, "aggregator")
        for key, value in values.items():
            _check_size(value, f"aggregator.{key}")
        class_token = bool(cfg.backbone.get("class_token", False))
        global_class = values.get("global_token") == "class"
        if global_class and not class_token:
            raise SemvprError(
                "aggregator.global_token=class needs backbone.class_token=true (a DINOv2 backbone's "
                "class token, after its patch channels)"
            )
        if class_token and not global_class:
            raise SemvprError(
                f"backbone.class_token=true is read only by aggregator=salad aggregator.global_token=class, "
                f"not by aggregator={cfg.aggregator.name}: set backbone.class_token=false"
            )
    except SemvprError as err:
        raise SemvprError(f"{prefix}{err}") from None


def _check_size(value: Any, key: str) -> None:
    """An aggregator size: whole numbers in [1, SIZE_MAX] (a list of them, or null), finite numbers > 0
    (dropout in [0, 1))."""
    if value is None or isinstance(value, str):
        return
    if isinstance(value, list):
        for i, item in enumerate(value):
            whole_number(item, f"{key}[{i}]", 1, SIZE_MAX)
    elif isinstance(value, bool):
        return
    elif isinstance(value, int):
        whole_number(value, key, 1, SIZE_MAX)
    elif key.endswith(".dropout"):
        number(value, key, 0, high=0.999)
    else:
        number(value, key, 0, above=True)


def _check_retrieval(cfg: DictConfig) -> None:
    typed(RunSettings, cfg, part=True)
    typed(OptimizerNode, cfg.recipe.optimizer, "recipe.optimizer", part=True)
    _check_trainer(cfg.trainer)
    _check_optimization(cfg)
    if cfg.get("ckpt_path") not in (None, "last"):
        from semvpr.core.checkpoint import read_checkpoint, read_weights

        contents = read_weights(cfg.ckpt_path)
        read_checkpoint(cfg.ckpt_path, contents)
        if "optimizer_states" not in contents:  # Lightning's KeyError once the caches were built
            raise SemvprError(
                f"ckpt_path={cfg.ckpt_path} holds the model's weights only (a run's tested.ckpt, for evaluation); a "
                "run resumes from its last.ckpt: ckpt_path=last hydra.run.dir=<its run dir>"
            )
    check_model(cfg)
    recipe = recipe_of(cfg)
    if isinstance(recipe, TripletRecipe) and recipe.negative_radius < recipe.positive_radius:
        raise SemvprError(
            f"recipe.negative_radius={cfg.recipe.negative_radius} is below recipe.positive_radius="
            f"{cfg.recipe.positive_radius}: a negative could then be a positive"
        )
    if isinstance(recipe, GsvRecipe) and str(cfg.trainer.get("strategy", "auto")).startswith("ddp"):
        raise SemvprError(
            f"recipe={recipe.name} mines its pairs within the whole batch on one device; use trainer=cpu or trainer=gpu"
        )
    eval_sets = cfg.data.get("eval_sets")
    if eval_sets is not None and cfg.data.get("eval_on") not in eval_sets:
        raise SemvprError(f"data.eval_on={cfg.data.get('eval_on')!r} is not one of {list(eval_sets)}")
    typed(DataNode, cfg.data, "data", part=True)
    typed(Features, cfg.features, "features")
    weighting = cfg.mask.weights
    evaluation = "ckpt" in cfg or OmegaConf.is_missing(cfg, "ckpt")  # the hub names its file as a value, not here
    if not evaluation and cfg.student.get("checkpoint"):
        raise SemvprError(
            f"student.checkpoint={cfg.student.checkpoint}: a saved student is read by semvpr.eval, localize and "
            "the hub (mask=student student.checkpoint=DIR); a training run trains its own: drop it"
        )
    if weighting == "learned" and cfg.mask._target_ is None:
        raise SemvprError(
            "mask=none has no mask to weight; mask.weights=learned (filter.weights=learned) needs "
            "mask=student, teacher or oracle (filter=unet, mask2former or oracle)"
        )
    if not evaluation:  # eval applies the invocation's control to the checkpoint's mask (config.restore)
        check_control_fits(cfg.mask, training=True)


def check_control_fits(mask: DictConfig, training: bool) -> None:
    """The mask control fits the mask it controls: there is a mask; ``objects``, ``sky`` and ``random`` make
    binary masks, which a model with learned class weights does not read; in ``training`` the unmasked side
    of ``mask.apply`` is weighted 1 per cell, which only a binary mask means."""
    control, apply = mask.control, mask.apply
    if mask._target_ is None:
        if control != "none":
            raise SemvprError(
                f"mask.control={control} needs a mask to control; mask=none has none (mask=student, teacher or oracle)"
            )
        if apply != "both":
            raise SemvprError(
                f"mask.apply={apply} needs a mask to apply; mask=none has none (mask=student, teacher or oracle)"
            )
    if mask.weights == "learned":
        if control in (*REMOVED_CLASSES, "random"):
            raise SemvprError(
                f"mask.control={control} makes a binary mask; mask.weights=learned weights class probabilities "
                "(use mask.weights=binary, or mask.control=shuffled)"
            )
        if training and apply != "both":
            raise SemvprError(
                f"mask.apply={apply} in training weights the other side 1 per cell, a binary mask; "
                "mask.weights=learned needs mask.apply=both"
            )


def _shown(value: Any) -> Any:
    """A config value as the user wrote it (lists as lists)."""
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


def _check_trainer(trainer: DictConfig) -> None:
    """The trainer's settings semvpr reads (``config.schema.TrainerSettings``), a precision this machine supports,
    and more than one device only with a DDP strategy (Lightning would otherwise relaunch the whole command line
    in a second process)."""
    settings = typed(TrainerSettings, trainer, "trainer", part=True)
    lightning_precision(settings.precision, settings.accelerator)  # supported here, or one line
    if not settings.strategy.startswith("ddp") and (settings.devices != 1 or settings.num_nodes != 1):
        raise SemvprError(
            f"trainer.devices={settings.devices} needs trainer=ddp (one process per device, started by semvpr); "
            f"without it use trainer.devices=1"
        )


def _check_optimization(cfg: DictConfig) -> None:
    """The recipe's optimizer and scheduler accept their settings: built on one parameter and stepped
    through the run's epochs (capped), so a value they refuse (``weight_decay=null``, ``step_size=0``) is
    one line before any work, not a TypeError at the first step or the fifth epoch."""
    import torch
    from hydra.utils import instantiate

    recipe = cfg.recipe
    refuse_mistyped_values(recipe.optimizer)
    refuse_mistyped_values(recipe.get("scheduler"))
    where = "recipe.optimizer"
    try:
        optimizer = instantiate(recipe.optimizer)([torch.nn.Parameter(torch.zeros(1))])
        if recipe.get("scheduler") is not None:
            where = "recipe.scheduler"
            scheduler = instantiate(recipe.scheduler)(optimizer)
            epochs = int(cfg.trainer.max_epochs)
            for _ in range(min(epochs if epochs > 0 else 1000, 1000)):
                optimizer.step()
                scheduler.step()
    except Exception as err:  # noqa: BLE001 - whatever the class raises is the reason
        target = OmegaConf.select(cfg, f"{where}._target_", default="?")
        raise SemvprError(f"{where} ({target}) refuses its settings: {type(err).__name__}: {err}") from None
    if not all(math.isfinite(group["lr"]) and group["lr"] >= 0 for group in optimizer.param_groups):
        raise SemvprError(f"{where}: the learning rate it schedules becomes {optimizer.param_groups[0]['lr']}")


def _check_segmentation(cfg: DictConfig) -> None:
    """semvpr.segment's settings, read after the segmenters have trained: checked before, not an error an hour in."""
    typed(SegNode, cfg.seg, "seg", part=True)
    typed(SegmentSettings, cfg, part=True)

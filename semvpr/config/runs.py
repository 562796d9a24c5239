"""Resuming a run continues it as it was composed, from the project's own config files.

``python -m semvpr.train ckpt_path=last hydra.run.dir=<run>`` continues the run with what it was
started with, not today's defaults: a resume without the original overrides is the same run. The run
directory is data written by someone, so its record is never run: the config is composed again from
the project's files with the config choices the run recorded (``<run>/.hydra/hydra.yaml``: e.g.
``filter=unet``, ``experiment=tiny``), which alone supply every ``_target_``, and the run's plain values
(``<run>/.hydra/config.yaml``) are checked against it as a checkpoint's record is
(``checkpoint.check_values``: known keys, the same kind of value, no ``_`` keys or interpolations
of its own) and applied. Overrides given with the resume must agree with that config; one that
contradicts it (another filter, another ``trainer.max_epochs``) is refused in one line before
anything is written. The run's ``.hydra`` record is left as it is (Hydra is told not to rewrite it).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from semvpr.core.checkpoint import check_values
from semvpr.core.errors import SemvprError
from semvpr.core.io import CONF_DIR, read_yaml

#: Overrides a resume may give freely: which checkpoint, and Hydra's own settings.
RESUME_KEYS = ("ckpt_path",)
_CHOICE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_\-]*$")


def _value(argv: list[str], key: str) -> str | None:
    """The value of ``key=...`` (with any leading ``+``) on a Hydra command line as Hydra reads it (a quoted
    path, as a sweep job's directory must be given, unquoted), last one wins."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    found = None
    for arg in argv:
        name, sep, value = arg.lstrip("+").partition("=")
        if sep and name == key:
            try:
                parsed = OverridesParser.create().parse_override(arg).value()
            except Exception:  # noqa: BLE001 - Hydra refuses it in its own line; keep the text as written
                parsed = value
            found = None if parsed is None else str(parsed)
    return found


def record_of_resumed_run(argv: list[str]) -> Path | None:
    """``<run>/.hydra/config.yaml`` if ``argv`` resumes an existing run (ckpt_path and hydra.run.dir);
    the run dir is taken as written, as Hydra takes it (no ``~`` expansion)."""
    ckpt, run = _value(argv, "ckpt_path"), _value(argv, "hydra.run.dir")
    if ckpt in (None, "", "null") or not run:
        return None
    record = Path(run) / ".hydra" / "config.yaml"
    return record if record.is_file() else None


def keep_run_record(argv: list[str]) -> list[str]:
    """Hydra's command line, told not to rewrite the ``.hydra`` record of a run being resumed."""
    return [*argv, "hydra.output_subdir=null"] if record_of_resumed_run(argv) is not None else argv


def _choices(record: Path) -> dict[str, str | None]:
    """The config choices a run recorded (``hydra.yaml``'s ``runtime.choices``), each naming one of the
    project's own config files or none (``experiment: null``); Hydra's own groups left out."""
    hydra_record = record.parent / "hydra.yaml"
    data = read_yaml(hydra_record, "run record") if hydra_record.is_file() else None
    choices = data.get("hydra", {}).get("runtime", {}).get("choices") if isinstance(data, dict) else None
    if not isinstance(choices, dict):
        raise SemvprError(f"{hydra_record} does not record the run's config choices; resume needs it")
    conf = Path(CONF_DIR)
    out: dict[str, str | None] = {}
    for group, choice in choices.items():
        if isinstance(group, str) and (group == "hydra" or group.startswith("hydra/")):
            continue
        if (
            not isinstance(group, str)
            or not _CHOICE.match(group)
            or not (choice is None or isinstance(choice, str) and _CHOICE.match(choice))
            or choice is not None
            and not (conf / group / f"{choice}.yaml").is_file()
        ):
            raise SemvprError(
                f"{hydra_record}: choice {group}={choice!r} is not one of the project's config files; "
                "a resume composes the run from them"
            )
        out[group] = choice
    return out


def resumed_config(
    cfg: DictConfig, record: Path, overrides: list[str], compose: Callable[[list[str]], DictConfig]
) -> DictConfig:
    """The run's own config, rebuilt (module docstring), with this invocation's ``ckpt_path``.

    ``cfg`` is what this invocation composed from ``overrides``; ``compose(overrides)`` composes the
    project's config with other overrides. Every key an override names (a group: every key below
    it), and every key where ``cfg`` differs from the plain default, must equal the run's own value.
    """
    where = f"resuming {record.parent.parent}"
    own_values = read_yaml(record, "run config")
    if not isinstance(own_values, dict):
        raise SemvprError(f"{record} is not a run config (a mapping)")
    choices = _choices(record)
    for override in overrides:  # another config file for a group (filter=, aggregator=): named as given
        group, _, value = override.lstrip("+~").partition("=")
        own_choice = (choices[group] or "null") if group in choices else value
        if value != own_choice:
            raise SemvprError(
                f"{where}: {override.lstrip('+')} contradicts the run's own {group}={own_choice}; "
                "a resume continues the run as it was started: drop the override"
            )
    schema = compose([f"{group}={choice}" for group, choice in choices.items() if choice is not None])
    project = OmegaConf.to_container(schema, resolve=False)
    check_values(own_values, project, f"{where}: ", source=f"a run's record ({record})", project_values=project)
    own = schema.copy()
    OmegaConf.set_struct(own, False)
    own.merge_with(own_values)
    OmegaConf.set_struct(own, True)

    named = {o.lstrip("+~").partition("=")[0] for o in overrides}
    default = compose([])
    given, base, theirs = (_leaves(OmegaConf.to_container(c, resolve=False)) for c in (cfg, default, own))
    for key in sorted(given.keys() | base.keys()):
        set_here = given.get(key) != base.get(key) or any(key == n or key.startswith(f"{n}.") for n in named)
        if key in RESUME_KEYS or not set_here:
            continue
        if given.get(key) != theirs.get(key):
            raise SemvprError(
                f"{where}: {key}={given.get(key)!r} contradicts the run's "
                f"own {key}={theirs.get(key)!r}; a resume continues the run as it was started: "
                f"drop the override"
            )
    own.ckpt_path = cfg.ckpt_path
    return own


def _leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted key -> plain value of every leaf (lists are leaves)."""
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for key, value in node.items():
            out.update(_leaves(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: node}


#: Hydra's own sweeper, whose jobs are the product of the swept values (:func:`record_plan`).
BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


def record_plan(config: DictConfig, sweep_dir: Path) -> None:
    """Write the overrides of every job a multirun is given into ``sweep_dir/jobs.json``
    (``reporting.sweep.JOBS_FILE``), as Hydra's basic sweeper makes them from its ``params`` and the command
    line, before the first job starts: the report of a stopped sweep counts the jobs that never started. With
    another sweeper (its jobs are not known beforehand) an earlier launch's list is removed."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from semvpr.core.io import write_json
    from semvpr.reporting.sweep import JOBS_FILE

    sweeper = OmegaConf.select(config, "hydra.sweeper")
    target = sweeper.get("_target_") if sweeper is not None else None
    if target != BASIC_SWEEPER:
        (sweep_dir / JOBS_FILE).unlink(missing_ok=True)
        return
    params = OmegaConf.to_container(sweeper.get("params") or OmegaConf.create({}), resolve=False)
    given = [f"{key}={value}" for key, value in params.items()]
    given += [str(o) for o in OmegaConf.to_container(config.hydra.overrides.task, resolve=False)]
    (batch,) = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(given), None)
    sweep_dir.mkdir(parents=True, exist_ok=True)
    write_json(sweep_dir / JOBS_FILE, {"jobs": [list(job) for job in batch]})

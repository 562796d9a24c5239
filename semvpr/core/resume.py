"""Resuming a run continues it as it was composed.

``python -m semvpr.train ckpt_path=last hydra.run.dir=<run>`` reloads ``<run>/.hydra/config.yaml``
(what the run was started with), not today's defaults: a resume without the original overrides
is the same run. Overrides given with the resume must agree with that config; one that
contradicts it (another filter, another ``trainer.max_epochs``) is refused in one line before
anything is written. The run's ``.hydra`` record is left as it is (Hydra is told not to rewrite it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from semvpr.core.errors import SemvprError

#: Overrides a resume may give freely: which checkpoint, and Hydra's own settings.
RESUME_KEYS = ("ckpt_path",)


def _value(argv: list[str], key: str) -> str | None:
    """The value of ``key=...`` (with any leading ``+``) on a Hydra command line, last one wins."""
    found = None
    for arg in argv:
        name, sep, value = arg.lstrip("+").partition("=")
        if sep and name == key:
            found = value
    return found


def record_of_resumed_run(argv: list[str]) -> Path | None:
    """``<run>/.hydra/config.yaml`` if ``argv`` resumes an existing run (ckpt_path and hydra.run.dir)."""
    ckpt, run = _value(argv, "ckpt_path"), _value(argv, "hydra.run.dir")
    if ckpt in (None, "", "null") or not run:
        return None
    record = Path(run).expanduser() / ".hydra" / "config.yaml"
    return record if record.is_file() else None


def keep_run_record(argv: list[str]) -> list[str]:
    """Hydra's command line, told not to rewrite the ``.hydra`` record of a run being resumed."""
    return [*argv, "hydra.output_subdir=null"] if record_of_resumed_run(argv) is not None else argv


def resumed_config(cfg: DictConfig, default: DictConfig, record: Path, overrides: list[str]) -> DictConfig:
    """The run's own config (``record``) with this invocation's ``ckpt_path``.

    ``cfg`` is what this invocation composed from ``overrides``, ``default`` what it would compose
    without them: every key an override names (a group: every key below it), and every key where
    the two differ, must equal the run's own value.
    """
    named = {o.lstrip("+~").partition("=")[0] for o in overrides}
    try:
        own = OmegaConf.load(record)
    except Exception as err:  # noqa: BLE001 - a damaged record gets one line
        raise SemvprError(f"{record} is not a readable run config ({type(err).__name__}); resume needs it") from None
    if not isinstance(own, DictConfig):
        raise SemvprError(f"{record} is not a run config (a mapping)")
    given, base, theirs = (_leaves(OmegaConf.to_container(c, resolve=False)) for c in (cfg, default, own))
    for key in sorted(given.keys() | base.keys()):
        set_here = given.get(key) != base.get(key) or any(key == n or key.startswith(f"{n}.") for n in named)
        if key in RESUME_KEYS or not set_here:
            continue
        if given.get(key) != theirs.get(key):
            raise SemvprError(
                f"resuming {record.parent.parent}: {key}={given.get(key)!r} contradicts the run's "
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

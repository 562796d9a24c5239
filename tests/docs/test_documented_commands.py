"""Every command the docs show composes; those that need nothing the tests lack run (tests/docs/documented_commands.py
has the substitution rule); the launchers the docs name compose, and submitit's local launcher runs a sweep."""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from semvpr.config.checks import check_overrides
from semvpr.core.device import visible_gpus
from semvpr.core.errors import SemvprError
from semvpr.core.io import CONF_DIR
from tests.docs.documented_commands import (
    HYDRA_COMMANDS,
    REPO,
    Command,
    collect,
    composable,
    first_of_each_sweep,
    placeholders,
)

COMMANDS = collect()
PARSERS = {
    "semvpr.report": "semvpr.report",
    "semvpr.evaltable": "semvpr.evaltable",
    "semvpr.data.synthcity": "semvpr.data.synthcity",
    "semvpr.data.inspect": "semvpr.data.inspect",
    "semvpr.reporting.claims": "semvpr.reporting.claims",
}


def test_the_docs_show_commands_of_every_kind() -> None:
    """The collector finds the commands (an empty list would pass every test below)."""
    modules = {c.module for c in COMMANDS}
    assert {"semvpr.train", "semvpr.eval", "semvpr.segment", "semvpr.localize", "semvpr.report"} <= modules
    assert any(c.where.startswith("conf/") for c in COMMANDS) and any(c.where.startswith("README") for c in COMMANDS)
    unknown = {c.module for c in COMMANDS} - set(HYDRA_COMMANDS) - set(PARSERS)
    assert not unknown, f"documented commands of no known module: {unknown}"


@pytest.mark.parametrize("command", COMMANDS, ids=[c.where for c in COMMANDS])
def test_a_documented_command_composes(command: Command) -> None:
    """The overrides parse and apply to the project's config (every swept group choice, the launcher and its
    settings included), or the argparse command line parses."""
    args = composable(command.args)
    if command.module in PARSERS:
        module = __import__(PARSERS[command.module], fromlist=["parser"])
        parser: argparse.ArgumentParser = module.parser()
        if command.needs and command.needs.startswith("its arguments"):
            return  # the command is only named (a table of commands)
        parsed = parser.parse_args(args)
        if command.module == "semvpr.data.inspect":
            check_overrides(parsed.overrides, "train")
        return
    config = HYDRA_COMMANDS[command.module]
    try:
        check_overrides(args, config)
    except SemvprError as err:
        pytest.fail(f"{command.where}: {command.text}\n  does not compose: {err}")
    job = [a for a in first_of_each_sweep(tuple(args)) if a not in ("-m", "--multirun")]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        compose(config_name=config, overrides=job, return_hydra_config=True)


@pytest.mark.parametrize(
    "launcher",
    [
        ["hydra/launcher=basic"],
        ["hydra.launcher.n_jobs=3"],
        ["hydra/launcher=joblib"],
        ["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=30"],
        [
            "hydra/launcher=submitit_slurm",
            "hydra.launcher.partition=gpu",
            "hydra.launcher.gpus_per_node=1",
            "hydra.launcher.timeout_min=720",
        ],
    ],
    ids=lambda a: a[0],
)
@pytest.mark.parametrize("config", ["train", "eval"])
def test_every_launcher_composes_with_its_own_settings(launcher: list[str], config: str) -> None:
    """The two-at-a-time setting belongs to the joblib launcher: the others compose without it."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    check_overrides(["-m", *launcher, "experiment=tiny", "seed=0,1"], config)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name=config, overrides=[*launcher, "experiment=tiny"], return_hydra_config=True)
    chosen = cfg.hydra.runtime.choices["hydra/launcher"]
    assert ("n_jobs" in cfg.hydra.launcher) == (chosen in ("joblib", "side_by_side"))
    if launcher == ["hydra.launcher.n_jobs=3"]:
        assert chosen == "side_by_side" and cfg.hydra.launcher.n_jobs == 3
    if chosen == "side_by_side":  # jobs_per_gpu reaches the count of GPU jobs side by side
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            gpu = compose(config_name=config, overrides=["trainer=gpu", "jobs_per_gpu=3"], return_hydra_config=True)
        assert gpu.hydra.launcher.n_jobs == 3 * max(1, len(visible_gpus()))
    if chosen == "submitit_slurm":  # the README's SLURM job: its settings reach the launcher's config
        slurm = cfg.hydra.launcher
        assert (slurm.partition, slurm.gpus_per_node, slurm.timeout_min) == ("gpu", 1, 720)


def test_a_setting_the_launcher_lacks_is_one_line_naming_it() -> None:
    proc = _run("semvpr.train", ["-m", "hydra/launcher=basic", "hydra.launcher.n_jobs=3", "seed=0,1"], REPO)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.strip() == (
        "semvpr: error: hydra.launcher.n_jobs is not a setting of the basic launcher (hydra/launcher=basic); "
        "its settings: none"
    )
    proc = _run("semvpr.eval", ["-m", "hydra/launcher=slurm", "ckpt=none", "seed=0,1"], REPO)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    assert proc.stderr.startswith("semvpr: error: hydra/launcher=slurm: no such launcher here (installed: basic")


@pytest.mark.parametrize(
    ("value", "line"),
    [
        # joblib's ValueError traceback once the sweep had started
        ("0", r"^hydra\.launcher\.n_jobs=0 must be a whole number other than 0 \(jobs at once; -1: one per core\)$"),
        # 'is not a setting of the side_by_side launcher', though it is one
        ("abc", r"^hydra\.launcher\.n_jobs=abc: Value 'abc' of type 'str' could not be converted to Integer$"),
        ("1.5", r"^hydra\.launcher\.n_jobs=1\.5: Value '1\.5' of type 'float' could not be converted to Integer$"),
    ],
)
def test_a_launcher_setting_of_the_wrong_value_is_one_line_naming_it(value: str, line: str) -> None:
    from semvpr.config.checks import check_overrides
    from semvpr.core.errors import SemvprError

    with pytest.raises(SemvprError, match=line):
        check_overrides(["-m", f"hydra.launcher.n_jobs={value}", "seed=0,1"], "train")
    check_overrides(["-m", "hydra.launcher.n_jobs=-1", "seed=0,1"], "train")  # joblib: one job per core


def _run(module: str, args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, capture_output=True, text=True, timeout=1200)


@pytest.mark.slow
def test_the_documented_commands_run(tmp_path: Path) -> None:
    """Rule 3: each command that needs nothing the tests lack runs on the tiny preset, swept lists cut to
    their first value, in the test's own run and cache directories; a command that needs a checkpoint of
    the user's (and nothing else) runs on the checkpoint of the first training command."""
    cache = f"paths.cache_dir={tmp_path / 'cache'}"
    runnable = {(c.module, tuple(first_of_each_sweep(c.args))): c for c in COMMANDS if c.needs is None}
    assert len(runnable) >= 10, runnable
    checkpoint: Path | None = None
    for number, ((module, args), command) in enumerate(
        sorted(runnable.items(), key=lambda kv: kv[0][0] != "semvpr.train")
    ):
        where = tmp_path / f"run{number}"
        extra = [cache, "threads=1"]
        if module in HYDRA_COMMANDS:
            multirun = "-m" in args
            extra += ["experiment=tiny", f"hydra.{'sweep' if multirun else 'run'}.dir={where}"]
        else:  # data.inspect: the tiny preset of the default set
            extra = ["experiment=tiny", cache]
        if module == "semvpr.eval" and "ckpt=none" in args:
            extra += ["init.overrides=['preset=tiny']"]
        proc = _run(module, [*args, *extra], REPO)
        assert proc.returncode == 0, f"{command.where}: {command.text}\n{proc.stderr[-3000:]}"
        found = sorted(where.rglob("tested.ckpt"))
        checkpoint = checkpoint or (found[0] if found else None)
    assert checkpoint is not None
    with_checkpoint = [c for c in COMMANDS if c.needs and "ckpt=" in c.needs and c.module == "semvpr.eval"]
    only_checkpoint = [c for c in with_checkpoint if [a.partition("=")[0] for a in placeholders(c.args)] == ["ckpt"]]
    assert only_checkpoint, "no documented evaluation of a checkpoint"
    for number, command in enumerate(only_checkpoint):
        args = [f"ckpt='{checkpoint}'" if a.startswith("ckpt=") else a for a in command.args]
        multirun = "-m" in args
        where = tmp_path / f"eval{number}"
        proc = _run(
            "semvpr.eval", [*args, cache, "threads=1", f"hydra.{'sweep' if multirun else 'run'}.dir={where}"], REPO
        )
        assert proc.returncode == 0, f"{command.where}: {command.text}\n{proc.stderr[-3000:]}"
        assert list(where.rglob("eval.json")), command.where


@pytest.mark.slow
def test_submitit_local_runs_the_four_way_sweep_with_one_shared_cache(tmp_path: Path) -> None:
    """The cluster path with a real scheduler's plugin: submitit's local launcher runs the tiny four-way sweep
    as separate processes over one cache (the teacher built once while the others wait on its lock), and the
    report is written once, at the end."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    sweep = tmp_path / "sweep"
    proc = _run(
        "semvpr.train",
        [
            "-m",
            "hydra/launcher=submitit_local",
            "hydra.launcher.timeout_min=30",
            "hydra.launcher.gpus_per_node=0",
            "experiment=tiny",
            "filter=none,attention,unet,mask2former",
            f"paths.cache_dir={tmp_path / 'cache'}",
            f"hydra.sweep.dir={sweep}",
            "threads=1",
        ],
        REPO,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = [json.loads(p.read_text()) for p in sweep.rglob("metrics.json")]
    assert sorted(j["filter"] for j in jobs) == ["attention", "mask2former", "none", "unet"]
    assert all(j["status"] == "ok" for j in jobs)
    teachers = [p for p in (tmp_path / "cache").iterdir() if p.name.startswith("teacher-")]
    assert len(teachers) == 1
    assert (sweep / "results.md").is_file() and (sweep / "results.csv").is_file()
    assert proc.stdout.count("results.md") <= 1 and proc.stderr.count("wrote the report") <= 1


@pytest.mark.parametrize(
    "command", ["eval", *(pytest.param(c, marks=pytest.mark.slow) for c in ("train", "localize", "segment", "label"))]
)
def test_help_says_what_the_command_does_its_settings_and_examples_not_the_config(command: str) -> None:
    """``--help`` was Hydra's stock config dump (241 lines); each command's says what it does, its main settings
    (every group option it names is one of the project's config files) and examples."""
    proc = subprocess.run(
        [sys.executable, "-m", f"semvpr.{command}", "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert lines[0].startswith(f"semvpr.{command}: ") and "Examples:" in lines and len(lines) < 40
    assert "_target_" not in proc.stdout and f"python -m semvpr.{command} " in proc.stdout
    groups = {p.name for p in (REPO / "conf").iterdir() if p.is_dir()}
    for group, options in re.findall(r"\b([a-z_]+)=([a-z0-9_]+(?:\|[a-z0-9_]+)+)", proc.stdout):
        if group in groups:
            assert all((REPO / "conf" / group / f"{o}.yaml").is_file() for o in options.split("|")), (group, options)

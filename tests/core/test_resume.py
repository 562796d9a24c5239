"""A resume continues the run as it was started: its own config, its .hydra record untouched."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import DictConfig, OmegaConf

from semvpr.config.runs import keep_run_record, resumed_config
from semvpr.core.errors import SemvprError
from tests.helpers import REPO, config, tiny_config


def train_cli(cwd: Path, *overrides: str) -> subprocess.CompletedProcess:
    """``python -m semvpr.train`` from ``cwd`` (where a default outputs/ would land)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-m", "semvpr.train", *overrides],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


CHOICES = {
    "data": "synthcity",
    "backbone": "efficientnet_lite0",
    "aggregator": "sral",
    "mask": "student",
    "filter": "unet",
    "teacher": "mask2former",
    "student": "unet",
    "recipe": "triplet",
    "trainer": "cpu",
    "logger": "default",
    "experiment": "tiny",
    "hydra/launcher": "basic",
}


def write_run_record(run: Path, own: DictConfig, choices: dict | None = None) -> Path:
    """A run's .hydra record as Hydra writes it: the composed config (unresolved) and its choices."""
    (run / ".hydra").mkdir(parents=True, exist_ok=True)
    OmegaConf.save(own, run / ".hydra" / "config.yaml")
    hydra_yaml = {"hydra": {"runtime": {"choices": choices or CHOICES}}}
    (run / ".hydra" / "hydra.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(hydra_yaml)))
    return run / ".hydra" / "config.yaml"


def compose(overrides: list[str]) -> DictConfig:
    return config(*overrides)


def test_a_resume_takes_the_runs_own_config_and_refuses_what_contradicts_it(tmp_path: Path) -> None:
    own = tiny_config(tmp_path / "cache", "trainer.max_epochs=3", "filter=unet")
    record = write_run_record(tmp_path / "run", own)
    resumed = resumed_config(config("ckpt_path=last"), record, ["ckpt_path=last"], compose)
    assert (resumed.trainer.max_epochs, resumed.filter.name, resumed.ckpt_path) == (3, "unet", "last")
    assert resumed.data.preset == own.data.preset == "tiny" and resumed.paths.cache_dir == own.paths.cache_dir
    assert OmegaConf.to_container(resumed, resolve=True) == {
        **OmegaConf.to_container(own, resolve=True),
        "ckpt_path": "last",
    }
    # Repeating the original overrides agrees with the record; another value does not.
    again = ["ckpt_path=last", "experiment=tiny", "filter=unet", "trainer.max_epochs=3"]
    assert resumed_config(config(*again), record, again, compose).trainer.max_epochs == 3
    for override, message in (
        ("trainer.max_epochs=5", "trainer.max_epochs=5 contradicts the run's own trainer.max_epochs=3"),
        # Another config file for a group is named as given, not by the first key it changes.
        ("filter=none", "filter=none contradicts the run's own filter=unet;"),
        ("aggregator=gem", "aggregator=gem contradicts the run's own aggregator=sral;"),
    ):
        with pytest.raises(SemvprError, match=message):
            resumed_config(config("ckpt_path=last", override), record, ["ckpt_path=last", override], compose)
    # Hydra is told not to rewrite the run's .hydra record; a fresh run is left alone.
    argv = ["ckpt_path=last", f"hydra.run.dir={tmp_path / 'run'}"]
    assert keep_run_record(argv) == [*argv, "hydra.output_subdir=null"]
    assert keep_run_record([f"hydra.run.dir={tmp_path / 'new'}", "ckpt_path=last"])[-1] != "hydra.output_subdir=null"


def _tampered(own: DictConfig, dotted: str, value: object) -> DictConfig:
    data = OmegaConf.to_container(own, resolve=False)
    node = data
    *parents, last = dotted.split(".")
    for key in parents:
        node = node.setdefault(key, {})
    node[last] = value
    return OmegaConf.create(data)


@pytest.mark.parametrize(
    "dotted,value,message",
    [
        # The run dir's record used to be instantiated as it was: this created a file outside the run.
        (
            "data.train",
            {"_target_": "builtins.open", "file": "PWNED", "mode": "w"},
            r"data\.train\._target_ is refused",
        ),
        ("recipe.optimizer._target_", "shutil.copyfile", r"recipe\.optimizer\._target_ is refused"),
        ("paths.cache_dir", "${oc.env:HOME}/x", r"paths\.cache_dir=.*interpolations are never read"),
        ("model.evil", 1, r"model\.evil is not a key"),
        ("model.num_clusters", "8", r"model\.num_clusters='8' has the wrong type"),
    ],
)
def test_a_tampered_run_record_is_refused_before_anything_runs(
    tmp_path: Path, dotted: str, value: object, message: str
) -> None:
    own = tiny_config(tmp_path / "cache", "filter=unet")
    record = write_run_record(tmp_path / "run", _tampered(own, dotted, value))
    with pytest.raises(SemvprError, match=message) as err:
        resumed_config(config("ckpt_path=last"), record, ["ckpt_path=last"], compose)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "PWNED").exists()


@pytest.mark.parametrize(
    "choices,message",
    [
        ({**CHOICES, "data": "../../evil"}, r"choice data='\.\./\.\./evil' is not one of the project's config files"),
        ({**CHOICES, "evil": "x"}, r"choice evil='x' is not one of"),
        (None, "does not record the run's config choices"),
    ],
)
def test_a_run_record_must_name_the_projects_own_choices(tmp_path: Path, choices: dict | None, message: str) -> None:
    record = write_run_record(tmp_path / "run", tiny_config(tmp_path / "cache"), choices)
    if choices is None:
        (tmp_path / "run" / ".hydra" / "hydra.yaml").write_text("hydra: {}\n")
    with pytest.raises(SemvprError, match=message):
        resumed_config(config("ckpt_path=last"), record, ["ckpt_path=last"], compose)


@pytest.mark.slow
def test_resume_reloads_the_runs_own_config_and_refuses_contradictions(tmp_path: Path) -> None:
    run, cache, cwd = tmp_path / "run", tmp_path / "cache", tmp_path / "cwd"
    cwd.mkdir()
    start = train_cli(
        cwd, "experiment=tiny", f"paths.cache_dir={cache}", "trainer.max_epochs=1", f"hydra.run.dir={run}"
    )
    assert start.returncode == 0, start.stderr[-2000:]
    record = {p.name: p.read_text() for p in (run / ".hydra").iterdir()}
    first = json.loads((run / "metrics.json").read_text())
    (run / "checkpoints" / "tested.ckpt").rename(tmp_path / "tested.ckpt")

    # The README's resume command with an override that contradicts the run: one line, nothing written.
    refused = train_cli(cwd, "ckpt_path=last", "trainer.max_epochs=3", f"hydra.run.dir={run}")
    assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0, refused.stderr[-2000:]
    assert "trainer.max_epochs=3 contradicts the run's own trainer.max_epochs=1" in refused.stderr
    assert json.loads((run / "metrics.json").read_text()) == first  # the refused command removed it
    weights_only = train_cli(cwd, f"ckpt_path={tmp_path / 'tested.ckpt'}", f"hydra.run.dir={run}")
    assert "holds the model's weights only" in weights_only.stderr, weights_only.stderr[-2000:]
    assert json.loads((run / "metrics.json").read_text()) == first

    # Without the original overrides it is still the same run (before: the default config, 1 epoch, status ok).
    resumed = train_cli(cwd, "ckpt_path=last", f"hydra.run.dir={run}")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    again = json.loads((run / "metrics.json").read_text())
    assert again["status"] == "ok" and again["recalls"] == first["recalls"]
    assert {p.name: p.read_text() for p in (run / ".hydra").iterdir()} == record
    assert list(cwd.iterdir()) == []  # nothing composed from today's defaults (outputs/cache) appeared


def test_a_sweep_jobs_run_started_with_threads_1_is_resumed_by_the_quoted_command(tmp_path: Path) -> None:
    """A sweep job's directory holds '=' and ',' (its overrides), so its resume command quotes it as Hydra
    needs: the record is still found (and Hydra told not to rewrite it), and a run started with a number of
    threads (threads=1 on a shared machine) is its own config, not a value of the wrong type."""
    job = tmp_path / "sweep" / "experiment=tiny,filter=unet,seed=3,threads=1"
    own = tiny_config(tmp_path / "cache", "filter=unet", "seed=3", "threads=1")
    record = write_run_record(job, own)
    argv = ["ckpt_path=last", f"hydra.run.dir='{job}'"]
    assert keep_run_record(argv) == [*argv, "hydra.output_subdir=null"]
    resumed = resumed_config(config("ckpt_path=last"), record, ["ckpt_path=last"], compose)
    assert (resumed.threads, resumed.seed, resumed.filter.name) == (1, 3, "unet")
    for bad in (True, 1.5):  # still a whole number or a word
        with pytest.raises(SemvprError, match="threads=.* has the wrong type"):
            resumed_config(config("ckpt_path=last"), write_run_record(job, _tampered(own, "threads", bad)), [], compose)


def test_resuming_from_a_checkpoint_of_weights_only_is_one_line_naming_last_ckpt(tmp_path: Path) -> None:
    """tested.ckpt holds the weights only (for eval); Lightning's KeyError came after the trunk pass."""
    from semvpr.config.checks import check_config
    from tests.helpers import write_checkpoint

    tested = tmp_path / "tested.ckpt"
    write_checkpoint(tiny_config(tmp_path), tested)
    with pytest.raises(SemvprError, match=r"holds the model's weights only .* ckpt_path=last hydra\.run\.dir="):
        check_config(tiny_config(tmp_path, f"ckpt_path={tested}"))


def test_ckpt_path_last_on_a_run_without_last_ckpt_is_refused_and_leaves_the_run_as_it_was(tmp_path: Path) -> None:
    """Lightning trains from scratch where ``last`` finds no checkpoint (a warning only), over the finished run's
    metrics.json and checkpoints."""
    run, cwd = tmp_path / "run", tmp_path / "cwd"
    cwd.mkdir()
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "tested.ckpt").write_bytes(b"the finished run's weights")
    (run / "metrics.json").write_text('{"status": "ok"}')
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    refused = train_cli(cwd, "ckpt_path=last", f"hydra.run.dir={run}")
    assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0, refused.stderr[-2000:]
    assert f"ckpt_path=last: {run} has no checkpoints/last.ckpt to resume from" in refused.stderr
    assert {p: p.read_bytes() for p in before} == before  # Hydra's job log may be added, nothing else changed
    assert list(cwd.iterdir()) == []

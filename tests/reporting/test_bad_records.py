"""Hostile sweep records (alias bombs, folders where files belong, deep JSON, markup in values) read by the
report and evaltable: cheap, escaped, and a failed row where a job's record is unreadable."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.bad_input import EVAL_SIZE, cli, dangling, files
from tests.helpers import make_folder


def _eval_json(job: dict, **extra: object) -> dict:
    return {
        "status": "ok",
        "data": "folder",
        "set": "a",
        "benchmark": None,
        "model": "m",
        "aggregator": "a",
        "mask": "none",
        "checkpoint": "/abs/machine/path/tested.ckpt",
        **{f"test/R@{n}": 1.0 for n in (1, 5, 10, 20)},
        "queries": 1,
        "database": 1,
        "descriptor_dim": 1,
        "wall_s": 1.0,
        **job,
        **extra,
    }


def _metrics(**labels: object) -> dict:
    return {
        "status": "ok",
        "error": None,
        "mask": "none",
        "weights": "binary",
        "backbone": "efficientnet_lite0",
        "backbone_weights": "imagenet",
        "seed": 0,
        **{f"test/R@{n}": 50.0 + n for n in (1, 5, 10, 20)},
        "wall_time_s": 1.0,
        "baseline_aggregator": False,
        **labels,
    }


def _alias_bomb(levels: int = 8, as_list: bool = False) -> str:
    """A few hundred bytes of YAML whose aliases expand to 9**levels strings."""
    prefix = "- " if as_list else ""
    lines = [f'{prefix}{"" if as_list else "a0: "}&a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, levels + 1):
        lines.append(f"{prefix}{'' if as_list else f'a{i}: '}&a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]")
    lines.append(f"{prefix}{'' if as_list else 'seed: '}*a{levels}" if not as_list else "- data=folder")
    return "\n".join(lines) + "\n"


def _sweep_with(tmp: Path, kind: str) -> Path:
    sweep = tmp / "sweep"
    if kind == "report":
        for name, agg in (("a", "netvlad"), ("b", "gem")):
            (sweep / name).mkdir(parents=True)
            (sweep / name / "metrics.json").write_text(
                json.dumps(_metrics(aggregator=agg, baseline_aggregator=agg == "netvlad"))
            )
    else:
        for name in ("0", "1"):
            (sweep / name / ".hydra").mkdir(parents=True)
            (sweep / name / "eval.json").write_text(json.dumps(_eval_json({})))
    return sweep


def test_an_alias_bomb_in_a_sweeps_record_costs_nothing(tmp_path: Path) -> None:
    """A 400-byte YAML alias bomb as a job's config.yaml (report) or overrides.yaml (evaltable) once cost
    minutes and gigabytes; aliases are refused where a run's record is read."""
    report = _sweep_with(tmp_path / "r", "report")
    (report / "a" / ".hydra").mkdir()
    (report / "a" / ".hydra" / "config.yaml").write_text(_alias_bomb())
    table = _sweep_with(tmp_path / "e", "evaltable")
    (table / "0" / "eval.json").write_text(json.dumps({"status": "failed", "error": "x"}))
    (table / "0" / ".hydra" / "overrides.yaml").write_text(_alias_bomb(as_list=True))
    for module, sweep in (("semvpr.report", report), ("semvpr.evaltable", table)):
        proc = cli(module, str(sweep), cwd=tmp_path, timeout=600, limit_gb=3)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert (sweep / "results.md").is_file()


def test_a_sweep_whose_results_md_is_a_folder_is_one_line_and_moves_nothing(tmp_path: Path) -> None:
    for module, kind in (("semvpr.report", "report"), ("semvpr.evaltable", "evaltable")):
        sweep = _sweep_with(tmp_path / kind, kind)
        (sweep / "results.md").mkdir()
        before = files(sweep)
        proc = cli(module, str(sweep), cwd=tmp_path)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and "results.md is a directory" in lines[0], proc.stderr
        assert files(sweep) == before  # nothing moved in beside the old report (no new csv, no figure)


@pytest.mark.parametrize("given", ["", "a_file", "absent"])
def test_a_sweep_dir_that_is_empty_a_file_or_absent_is_one_line_and_writes_nothing(tmp_path: Path, given: str) -> None:
    """An empty name read the working directory as the sweep and wrote results.md there."""
    _sweep_with(tmp_path, "report")  # the working directory holds a sweep's jobs: an empty name must not find them
    (tmp_path / "a_file").write_text("x")
    problem = {"": "sweep dir: an empty name names no folder", "a_file": "a_file is a file", "absent": "does not exist"}
    for module in ("semvpr.report", "semvpr.evaltable"):
        before = files(tmp_path)
        proc = cli(module, given, cwd=tmp_path, timeout=600)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and problem[given] in lines[0], proc.stderr
        assert "pass the multirun dir" in lines[0] and files(tmp_path) == before


def test_deeply_nested_json_in_a_sweep_is_a_failed_row(tmp_path: Path) -> None:
    for module, kind, name in (
        ("semvpr.report", "report", "a/metrics.json"),
        ("semvpr.evaltable", "evaltable", "1/eval.json"),
    ):
        sweep = _sweep_with(tmp_path / kind, kind)
        (sweep / name).write_text("[" * 100_000 + "]" * 100_000)
        proc = cli(module, str(sweep), cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert "not readable JSON" in (sweep / "results.md").read_text()


def test_evaltable_reads_overrides_as_text_and_escapes_every_cell(tmp_path: Path) -> None:
    sweep = _sweep_with(tmp_path, "evaltable")
    (sweep / "0" / ".hydra" / "overrides.yaml").write_text("- data=folder\n- data.root=${oc.env:SECRETV}\n")
    (sweep / "0" / "eval.json").write_text(json.dumps({"status": "failed", "error": "boom\n# Heading <script>x"}))
    hostile = {"data": "<script>alert(1)</script>", "set": "a\n# Injected heading\n<img src=x>", "benchmark": "<b>"}
    (sweep / "1" / "eval.json").write_text(json.dumps(_eval_json(hostile)))
    (sweep / "2").mkdir()
    (sweep / "2" / "eval.json").write_text(json.dumps({"status": "ok"}))  # keys missing: a failed row, no KeyError
    proc = cli("semvpr.evaltable", str(sweep), cwd=tmp_path, env={"SECRETV": "/home/secret-token-123"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    text = (sweep / "results.md").read_text()
    assert "secret-token" not in text and "data.root=${oc.env:SECRETV}" in text
    assert "<script" not in text and "<img" not in text and "<b>" not in text
    assert not [line for line in text.splitlines() if line.startswith(("# Injected", "# Heading"))]
    assert "eval.json has no usable 'data'" in text
    assert ", /abs/machine/path" not in text and "/abs/machine/path/tested.ckpt" in text  # relative to the sweep


def test_evaltable_names_a_failed_job_of_a_checkpoint_sweep_by_its_overrides(tmp_path: Path) -> None:
    sweep = _sweep_with(tmp_path, "evaltable")
    ckpt = tmp_path / "runs" / "a=1,b=2" / "tested.ckpt"
    (sweep / "1" / ".hydra" / "overrides.yaml").write_text(f"- ckpt='{ckpt}'\n- mask=student\n")
    (sweep / "1" / "eval.json").write_text(json.dumps({"status": "failed", "error": "no student"}))
    proc = cli("semvpr.evaltable", str(sweep), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    failed = [ln for ln in (sweep / "results.md").read_text().splitlines() if "failed: no student" in ln]
    assert len(failed) == 1 and failed[0].startswith("| ckpt=../runs/a=1,b=2/tested.ckpt mask=student |")


def _report_with_baseline_named(tmp_path: Path, name: str) -> Path:
    """The report of a two-job sweep whose baseline aggregator records ``name``; returns the sweep dir."""
    sweep = tmp_path / "sweep"
    for job, agg in (("a", name), ("b", "gem")):
        (sweep / job).mkdir(parents=True)
        (sweep / job / "metrics.json").write_text(json.dumps(_metrics(aggregator=agg, baseline_aggregator=job == "a")))
    proc = cli("semvpr.report", str(sweep), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return sweep


def test_report_escapes_the_gain_line_and_leaves_the_sweep_path_out(tmp_path: Path) -> None:
    text = (_report_with_baseline_named(tmp_path, "net`vlad</p>\n# HEAD <script>x</script>") / "results.md").read_text()
    assert "<script" not in text and "</p>" not in text and not any(ln.startswith("# HEAD") for ln in text.splitlines())
    assert str(tmp_path) not in text  # no absolute path of the machine that made it


def test_report_names_rows_by_the_preset_asked_for(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    presets = {"none": ("netvlad", "none"), "attention": ("sral", "none"), "unet": ("sral", "student")}
    for preset, (agg, mask) in presets.items():
        job = sweep / f"filter={preset},seed=0"
        job.mkdir(parents=True)
        labels = {"aggregator": agg, "mask": mask, "filter": preset, "baseline_aggregator": agg == "netvlad"}
        (job / "metrics.json").write_text(json.dumps(_metrics(**labels)))
    job = sweep / "aggregator=gem,seed=0"  # not asked for by a preset: named by what it ran
    job.mkdir()
    (job / "metrics.json").write_text(json.dumps(_metrics(aggregator="gem", filter="none")))
    proc = cli("semvpr.report", str(sweep), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = [
        ln.split("|")[2].strip() for ln in (sweep / "results.md").read_text().splitlines() if ln.startswith("| eff")
    ]
    assert rows == ["none (netvlad · none)", "gem · none", "attention (sral · none)", "unet (sral · student)"]


@pytest.mark.slow
def test_one_failing_job_of_an_eval_multirun_is_a_failed_row(tmp_path: Path, checkpoint: Path) -> None:
    good = make_folder(tmp_path / "good", n=3)
    broken = make_folder(tmp_path / "broken", n=3)
    dangling(broken / "images" / "test")
    sweep = tmp_path / "sweep"
    proc = cli(
        "semvpr.eval",
        "-m",
        "experiment=tiny",
        *EVAL_SIZE,
        f"ckpt={checkpoint}",
        "data=folder",
        f"data.root={broken},{good}",
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"hydra.sweep.dir={sweep}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [
        ln
        for ln in (sweep / "results.md").read_text().splitlines()
        if ln.startswith("| data=folder") or "measured" in ln
    ]
    assert len(rows) == 2 and "failed: " in rows[0] and "not found" in rows[0] and "measured" in rows[1]


def test_a_dollar_in_a_runs_labels_is_drawn_as_written_not_as_tex(tmp_path: Path) -> None:
    """matplotlib read '$...$' in a label as TeX: an aggregator named 'net$\\frac{$vlad' (or a setting's value)
    cost the sweep its R@1 figure ('skipped: ValueError: ... Expected \\frac{num}{den}')."""
    sweep = _report_with_baseline_named(tmp_path, "net$\\frac{$vlad")
    text = (sweep / "results.md").read_text()
    assert "skipped: ValueError" not in text and (sweep / "r1_by_aggregator.png").is_file()

"""Sweep report: aggregation numbers, table order, gains, failed jobs, figures, CLI and Hydra callback."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from PIL import Image

from semvpr.config.runs import BASIC_SWEEPER, record_plan
from semvpr.report import ReportCallback
from semvpr.reporting.sweep import load_sweep
from semvpr.reporting.sweep_report import write_report
from tests.helpers import REPO

NS = (1, 5, 10, 20)
# (filter, seed) -> R@1; R@N = R@1 + (N - 1) so every column has hand-checkable stats
R1 = {
    ("none", 1): 40.0,
    ("none", 2): 44.0,
    ("attention", 1): 38.0,
    ("attention", 2): 40.0,
    ("unet", 1): 48.0,
    ("unet", 2): 50.0,
    ("mask2former", 1): 50.0,
    ("mask2former", 2): 56.0,
    ("oracle", 1): 70.0,
}


def _png(path: Path, colour: tuple[int, int, int]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (20, 16), colour).save(path)
    return path


# The seed's filter presets as the (aggregator, mask) they select, and their display rows.
PRESETS = {
    "none": ("netvlad", "none"),
    "attention": ("sral", "none"),
    "unet": ("sral", "student"),
    "mask2former": ("sral", "teacher"),
    "oracle": ("sral", "oracle"),
}
ROW = {f: f"{a} · {m}" for f, (a, m) in PRESETS.items()}


def _labels(filter_: str, aggregator: str | None = None, mask: str | None = None) -> dict:
    """What a run records to be grouped by (semvpr.config.job.run_labels)."""
    aggregator = aggregator or PRESETS[filter_][0]
    mask = mask or PRESETS[filter_][1]
    return {
        "aggregator": aggregator,
        "baseline_aggregator": aggregator == "netvlad",
        "mask": mask,
        "mask_upper_bound": mask == "oracle",
        "weights": "binary",
        "filter": filter_,
    }


def _metrics(filter_: str, seed: int, r1: float, backbone: str = "vgg16", **labels: str) -> dict:
    m = {
        "status": "ok",
        "error": None,
        **_labels(filter_, **labels),
        "backbone": backbone,
        "seed": seed,
        "wall_time_s": 10.0 * seed,
        "best/epoch": seed + 3,
        "recalls": {str(n): min(100.0, r1 + n - 1) for n in range(1, 21)},
    }
    m.update({f"test/R@{n}": r1 + n - 1 for n in NS})
    return m


def _job(sweep: Path, name: str, metrics: dict | None) -> Path:
    job = sweep / name
    (job / ".hydra").mkdir(parents=True)
    if metrics is not None:
        (job / "metrics.json").write_text(json.dumps(metrics))
    return job


@pytest.fixture()
def sweep(tmp_path: Path) -> Path:
    """A hand-made multirun: 4 filters x 2 seeds + 1 oracle run, one failed job, one hard crash."""
    sweep = tmp_path / "multiruns" / "2024-01-01" / "12-00-00"
    queries = [_png(tmp_path / "data" / f"q{i}.png", (200, 40 * i, 0)) for i in range(2)]
    dbs = [_png(tmp_path / "data" / f"db{i}.png", (0, 40 * i, 200)) for i in range(3)]
    rng = np.random.default_rng(0)
    for (f, seed), r1 in R1.items():
        job = _job(sweep, f"filter={f},seed={seed}", _metrics(f, seed, r1))
        # The dataset root the run recorded: the report draws images from there only.
        (job / ".hydra" / "config.yaml").write_text(f"seed: {seed}\ndata:\n  root: {tmp_path / 'data'}\n")
        arrays: dict[str, np.ndarray] = {
            "query_index": np.array([0, 1]),
            "image_paths": np.array([str(q) for q in queries]),
        }
        if f != "none":
            arrays["attention"] = rng.random((2, 4, 5)).astype(np.float32)
        if f == "mask2former":
            arrays["teacher"] = (rng.random((2, 4, 5)) > 0.5).astype(np.float32)
        if f == "unet":
            arrays["student"] = (rng.random((2, 4, 5)) > 0.5).astype(np.float32)
        np.savez(job / "maps.npz", **arrays)
        topk = [{"path": str(d), "utm": [float(i), 0.0], "correct": i == 0 and f != "none"} for i, d in enumerate(dbs)]
        (job / "retrievals.json").write_text(
            json.dumps({"queries": [{"query": str(q), "utm": [0.0, 0.0], "topk": topk} for q in queries]})
        )
    _job(
        sweep,
        "filter=unet,seed=3",
        {
            "status": "failed",
            **_labels("unet"),
            "backbone": "vgg16",
            "seed": 3,
            "error": "Traceback (most recent call last):\n  File x\nRuntimeError: out of memory",
        },
    )
    crashed = _job(sweep, "filter=mask2former,seed=3", None)
    (crashed / ".hydra" / "overrides.yaml").write_text("- filter=mask2former\n- seed=3\n")
    (crashed / ".hydra" / "hydra.yaml").write_text(
        "hydra:\n  job:\n    name: train\n  runtime:\n    choices:\n      backbone: vgg16\n"
        "      aggregator: sral\n      mask: teacher\n      filter: mask2former\n"
    )
    return sweep


def _csv_rows(sweep: Path) -> dict[str, dict[str, str]]:
    with open(sweep / "results.csv", newline="") as fh:
        return {f"{r['aggregator']} · {r['mask']}": r for r in csv.DictReader(fh)}


def test_csv_means_and_sample_stds(sweep: Path) -> None:
    write_report(sweep)
    rows = {f: _csv_rows(sweep)[row] for f, row in ROW.items()}
    assert float(rows["none"]["R@1_mean"]) == pytest.approx(42.0)
    assert float(rows["none"]["R@1_std"]) == pytest.approx(2.8284, abs=1e-4)  # ddof=1 of 40, 44
    assert float(rows["mask2former"]["R@20_mean"]) == pytest.approx(72.0)
    assert float(rows["mask2former"]["R@20_std"]) == pytest.approx(4.2426, abs=1e-4)
    assert rows["oracle"]["R@1_std"] == ""  # one run: no std
    assert rows["unet"]["n"] == "2" and rows["unet"]["failed"] == "1" and rows["unet"]["seeds"] == "1 2"
    assert rows["mask2former"]["failed"] == "1"  # the hard crash is grouped by its .hydra choices
    assert float(rows["none"]["wall_time_s"]) == pytest.approx(15.0)
    assert rows["none"]["backbone"] == "vgg16"
    assert rows["none"]["best_epochs"] == "4 5" and rows["unet"]["best_epochs"] == "4 5"  # seeds 1, 2


def test_markdown_order_gains_failures_and_figures(sweep: Path) -> None:
    md = write_report(sweep)
    assert md == sweep / "results.md"
    text = md.read_text()
    table = [ln for ln in text.splitlines() if ln.startswith("| vgg16 |")]
    # Runs asked for by a preset are named by it, with the aggregator and mask it selected.
    assert [ln.split("|")[2].strip() for ln in table] == [
        "none (netvlad · none)",
        "attention (sral · none)",
        "unet (sral · student)",
        "mask2former (sral · teacher)",
        "oracle (sral · oracle, upper bound)",
    ]
    assert "| 42.0 ± 2.8 | 46.0 ± 2.8 | 51.0 ± 2.8 | 61.0 ± 2.8 | 2 | 1, 2 | 4, 5 | 0 | 15.0 |" in table[0]
    assert "| 70.0 ± – |" in table[4]
    # Paired by seed: attention 38-40, 40-44; the oracle has seed 1 only (70-40), not 70-mean(none).
    assert (
        "**R@1 gain over none (netvlad · none) (vgg16)**, per seed (same backbone init and data), then mean ± std: "
        "attention (sral · none) −3.0 ± 1.4 (better in 0 of 2 seeds), unet (sral · student) +7.0 ± 1.4 "
        "(better in 2 of 2 seeds), mask2former (sral · teacher) +11.0 ± 1.4 (better in 2 of 2 seeds), "
        "oracle (sral · oracle, upper bound) +30.0 (better in 1 of 1 seeds)"
    ) in text
    # the same aggregator without a mask: student 48-38, 50-40; teacher 50-38, 56-40; oracle 70-38
    assert (
        "- sral: student +10.0 ± 0.0 (better in 2 of 2 seeds), teacher +14.0 ± 2.8 (better in 2 of 2 seeds), "
        "oracle (upper bound) +32.0 (better in 1 of 1 seeds)"
    ) in text
    failed = [ln for ln in text.splitlines() if ln.startswith("- `filter=")]
    assert len(failed) == 2
    assert any("filter=unet,seed=3" in ln and ln.endswith("RuntimeError: out of memory") for ln in failed)
    assert any("filter=mask2former,seed=3" in ln and "vgg16" in ln and ln.endswith("no metrics.json") for ln in failed)
    assert "skipped" not in text
    for name in ("recall_at_n.png", "r1_by_aggregator.png", "figure3.png", "retrievals.png"):
        assert f"]({name})" in text
        with Image.open(sweep / name) as im:
            assert im.format == "PNG" and im.width > 200 and im.height > 200
            assert len(set(np.asarray(im.convert("L")).ravel().tolist())) > 10  # something was drawn
    assert not list(sweep.glob(".*.tmp"))  # temp files renamed away


def test_missing_inputs_skip_figures_with_note(tmp_path: Path) -> None:
    _job(tmp_path, "backbone=resnet50,filter=unet,seed=1", _metrics("unet", 1, 30.0, "resnet50"))
    _job(tmp_path, "backbone=vgg16,filter=none,seed=1", _metrics("none", 1, 20.0))
    text = write_report(tmp_path).read_text()
    assert "- `figure3.png` skipped: no job wrote maps.npz" in text
    assert "- `retrievals.png` skipped: no job wrote retrievals.json" in text
    assert "](recall_at_n.png)" in text and (tmp_path / "recall_at_n.png").stat().st_size > 0
    assert "**R@1 gain over none (netvlad · none) (resnet50):** no finished none (netvlad · none) run" in text
    assert "| resnet50 | unet (sral · student) | 30.0 ± – |" in text


def test_runs_that_differ_only_in_backbone_weights_get_their_own_rows(tmp_path: Path) -> None:
    """A sweep over backbone.weights=imagenet,none must not average the pretrained and random-init runs."""
    for seed, (r1_pre, r1_rand) in enumerate([(70.0, 12.0), (72.0, 14.0)]):
        _job(
            tmp_path,
            f"backbone.weights=imagenet,filter=none,seed={seed}",
            {**_metrics("none", seed, r1_pre, "efficientnet_lite0"), "backbone_weights": "imagenet"},
        )
        _job(
            tmp_path,
            f"backbone.weights=none,filter=none,seed={seed}",
            {**_metrics("none", seed, r1_rand, "efficientnet_lite0"), "backbone_weights": "none"},
        )
    # a job that died before metrics.json: its weights come from its composed config
    died = _job(tmp_path, "backbone.weights=none,filter=none,seed=2", None)
    (died / ".hydra" / "config.yaml").write_text("seed: 2\nbackbone:\n  name: efficientnet_lite0\n  weights: none\n")
    (died / ".hydra" / "hydra.yaml").write_text(
        "hydra:\n  runtime:\n    choices:\n      backbone: efficientnet_lite0\n"
    )
    text = write_report(tmp_path).read_text()
    assert "| efficientnet_lite0 | none (netvlad · none) | 71.0 ± 1.4 |" in text
    assert "| efficientnet_lite0 (random init) | none (netvlad · none) | 13.0 ± 1.4 |" in text
    assert {job.backbone for job in load_sweep(tmp_path).jobs} == {
        "efficientnet_lite0",
        "efficientnet_lite0 (random init)",
    }


def test_a_sweep_over_recipes_gives_each_recipe_its_own_rows(tmp_path: Path) -> None:
    """recipe=triplet,gsv must not average the two protocols: the other recipe is marked in the aggregator."""
    for seed, (r1_triplet, r1_gsv) in enumerate([(60.0, 70.0), (62.0, 74.0)]):
        for recipe, r1 in (("triplet", r1_triplet), ("gsv", r1_gsv)):
            _job(
                tmp_path,
                f"aggregator=mixvpr,mask=none,recipe={recipe},seed={seed}",
                {**_metrics("none", seed, r1, aggregator="mixvpr", mask="none"), "recipe": recipe},
            )
    # a job that died before metrics.json: its recipe comes from its composed choices
    died = _job(tmp_path, "aggregator=mixvpr,mask=none,recipe=gsv,seed=2", None)
    (died / ".hydra" / "hydra.yaml").write_text(
        "hydra:\n  runtime:\n    choices:\n      aggregator: mixvpr\n      recipe: gsv\n      mask: none\n"
    )
    text = write_report(tmp_path).read_text()
    assert "| vgg16 | mixvpr · none | 61.0 ± 1.4 |" in text
    assert "| vgg16 | mixvpr (gsv) · none | 72.0 ± 2.8 |" in text
    assert {job.aggregator for job in load_sweep(tmp_path).jobs} == {"mixvpr", "mixvpr (gsv)"}
    assert [j.ok for j in load_sweep(tmp_path).jobs if j.aggregator == "mixvpr (gsv)"].count(False) == 1


def test_a_sweep_over_any_other_setting_gives_each_value_its_own_rows(tmp_path: Path) -> None:
    """-m model.num_clusters=16,64 seed=0,1 averaged the two sizes as if they were four seeds of one run, and
    paired the masks' gains across them."""
    for seed in (0, 1):
        for clusters, r1 in ((16, 50.0), (64, 70.0)):
            for f, gain in (("none", 0.0), ("unet", 5.0)):
                job = _job(
                    tmp_path,
                    f"filter={f},model.num_clusters={clusters},seed={seed}",
                    _metrics(f, seed, r1 + gain + seed),
                )
                overrides = [f"filter={f}", f"model.num_clusters={clusters}", f"seed={seed}", "threads=1"]
                overrides += [f"paths.cache_dir=/c{seed}", "hydra.job.chdir=false"]  # neither makes a run another
                (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    text = write_report(tmp_path).read_text()
    assert "| vgg16 (model.num_clusters=16) | none (netvlad · none) | 50.5 ± 0.7 |" in text
    assert "| vgg16 (model.num_clusters=64) | unet (sral · student) | 75.5 ± 0.7 |" in text
    assert len({job.backbone for job in load_sweep(tmp_path).jobs}) == 2


def test_a_mask_control_is_named_in_its_rows_even_where_no_job_varies_it(tmp_path: Path) -> None:
    for seed in (0, 1):
        job = _job(tmp_path, f"filter=unet,mask.control=random,seed={seed}", _metrics("unet", seed, 60.0 + seed))
        overrides = ["filter=unet", "mask.control=random", "mask.apply=database", f"seed={seed}"]
        (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    text = write_report(tmp_path).read_text()
    assert "| vgg16 (mask.apply=database, mask.control=random) | unet (sral · student) | 60.5 ± 0.7 |" in text


def test_cli_without_job_dirs_exits_2_with_one_line(tmp_path: Path) -> None:
    for target in (tmp_path, tmp_path / "missing"):
        proc = subprocess.run(
            [sys.executable, "-m", "semvpr.report", str(target)], capture_output=True, text=True, cwd=REPO, timeout=600
        )
        assert proc.returncode == 2
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("semvpr: error:") and str(target) in lines[0]


def test_callback_resolves_relative_sweep_dir(sweep: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = sweep.parents[2]
    cfg = OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep.relative_to(root))}, "runtime": {"cwd": str(root)}}})
    ReportCallback().on_multirun_end(cfg)
    out = capsys.readouterr().out
    assert str(sweep / "results.md") in out and "| vgg16 | none (netvlad · none) | 42.0 ± 2.8 |" in out
    # a report failure is one stderr line, never an exception that would hide the sweep's results
    bad = OmegaConf.create({"hydra": {"sweep": {"dir": str(root / "nope")}}})
    ReportCallback().on_multirun_end(bad)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "report failed" in err[0]


def test_hydra_multirun_calls_callback(tmp_path: Path) -> None:
    """A real `-m` sweep with the callback configured writes results.md into hydra.sweep.dir."""
    (tmp_path / "app.py").write_text(
        textwrap.dedent("""
        import json, hydra
        from hydra.core.hydra_config import HydraConfig
        from pathlib import Path

        @hydra.main(version_base=None, config_path=".", config_name="cfg")
        def main(cfg):
            r1 = 30.0 + 10 * (cfg.mask == "student") + cfg.seed
            m = {"status": "ok", "aggregator": "gem", "baseline_aggregator": False, "mask": cfg.mask,
                 "backbone": "vgg16", "seed": cfg.seed, "wall_time_s": 1.0}
            m.update({f"test/R@{n}": r1 for n in (1, 5, 10, 20)})
            Path(HydraConfig.get().runtime.output_dir, "metrics.json").write_text(json.dumps(m))

        main()
    """)
    )
    (tmp_path / "cfg.yaml").write_text(
        textwrap.dedent("""
        mask: none
        seed: 1
        hydra:
          callbacks:
            report: {_target_: semvpr.report.ReportCallback}
          sweep: {dir: "multiruns/${now:%Y-%m-%d}/${now:%H-%M-%S}", subdir: "${hydra.job.override_dirname}"}
    """)
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [sys.executable, "app.py", "-m", "mask=none,student", "seed=1,2"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    (md,) = tmp_path.glob("multiruns/*/*/results.md")
    assert "| vgg16 | gem · student | 41.5 ± 0.7 |" in md.read_text()
    assert "- gem: student +10.0 ± 0.0 (better in 2 of 2 seeds)" in proc.stdout


def test_learned_weights_rows_gains_and_weights_figure(tmp_path: Path) -> None:
    from semvpr.data.classes import TRAIN_ID_NAMES

    for seed, (binary, learned, w_veg) in {1: (40.0, 43.0, 0.3), 2: (44.0, 43.0, 0.5)}.items():
        for filter_, r1 in (("oracle", binary), ("oracle+learned", learned)):
            metrics = _metrics("oracle", seed, r1)
            if filter_.endswith("learned"):
                metrics["weights"] = "learned"
                metrics["class_weights"] = {n: (w_veg if n == "vegetation" else 0.9) for n in TRAIN_ID_NAMES}
            _job(tmp_path, f"filter=oracle,filter.weights={filter_.partition('+')[2] or 'binary'},seed={seed}", metrics)
    text = write_report(tmp_path).read_text()
    rows = [ln.split("|")[2].strip() for ln in text.splitlines() if ln.startswith("| vgg16 |")]
    assert rows == ["oracle (sral · oracle, upper bound)", "oracle (sral · oracle+learned, upper bound)"]
    assert (
        "**R@1 gain of learned class weights over binary weights (vgg16)**, paired by seed: "
        "oracle (sral · oracle+learned, upper bound) +1.0 ± 2.8 (better in 1 of 2 seeds)"
    ) in text
    assert "| vegetation | 0.40 ± 0.14 |" in text and "| road | 0.90 ± 0.00 |" in text
    assert "](class_weights.png)" in text
    with Image.open(tmp_path / "class_weights.png") as im:
        assert im.format == "PNG" and im.width > 400
    # The learned runs gone, the next report draws no class weights, and the earlier figure goes with them.
    for job in tmp_path.glob("*filter.weights=learned*"):
        (job / "metrics.json").unlink()
        (job / ".hydra").rmdir()
        job.rmdir()
    assert "class_weights.png" not in write_report(tmp_path).read_text()
    assert not (tmp_path / "class_weights.png").exists() and (tmp_path / "recall_at_n.png").exists()


def test_aggregator_by_mask_matrix_and_bars(tmp_path: Path) -> None:
    # R@1 by (aggregator, mask, seed); R@5 = R@1 + 4 (see _metrics)
    r1 = {
        ("netvlad", "none"): (30.0, 34.0),
        ("netvlad", "oracle"): (35.0, 33.0),
        ("gem", "none"): (20.0, 22.0),
        ("gem", "student"): (26.0, 30.0),
        ("gem", "oracle"): (25.0, 27.0),
    }
    for (agg, mask), values in r1.items():
        for seed, value in enumerate(values):
            _job(
                tmp_path,
                f"aggregator={agg},mask={mask},seed={seed}",
                _metrics("none", seed, value, aggregator=agg, mask=mask),
            )
    text = write_report(tmp_path).read_text()
    matrix = text[text.index("## Aggregator × mask (vgg16)") :]
    lines = [ln for ln in matrix.splitlines() if ln.startswith("| ")]
    # baseline aggregator first; no mask first, upper bounds last
    assert lines[0] == "| aggregator | none | student | oracle (upper bound) |"
    assert lines[1] == "| netvlad | 32.0 ± 2.8 / 36.0 ± 2.8 | – | 34.0 ± 1.4 / 38.0 ± 1.4 |"
    assert lines[2] == "| gem | 21.0 ± 1.4 / 25.0 ± 1.4 | 28.0 ± 2.8 / 32.0 ± 2.8 | 26.0 ± 1.4 / 30.0 ± 1.4 |"
    # paired by seed against the same aggregator without a mask: gem student 26-20, 30-22
    assert "- netvlad: oracle (upper bound) +2.0 ± 4.2 (better in 1 of 2 seeds)" in matrix
    assert "- gem: student +7.0 ± 1.4 (better in 2 of 2 seeds), oracle (upper bound) +5.0 ± 0.0" in matrix
    # across aggregators, against the baseline without a mask: gem none 20-30, 22-34
    assert "gem · none −11.0 ± 1.4 (better in 0 of 2 seeds)" in text
    assert "](r1_by_aggregator.png)" in text
    with Image.open(tmp_path / "r1_by_aggregator.png") as im:
        assert im.format == "PNG" and im.width > 400
        assert len(set(np.asarray(im.convert("L")).ravel().tolist())) > 10


def test_the_sweep_directory_is_read_as_data(sweep: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from semvpr.reporting import sweep_report as report
    from semvpr.reporting.sweep import load_sweep

    # An override is a plain string: ${oc.env:...} is never resolved (it leaked the variable into results.md).
    monkeypatch.setenv("SEMVPR_TEST_SECRET", "hunter2")
    crashed = _job(sweep, "aggregator=evil,seed=4", None)
    (crashed / ".hydra" / "overrides.yaml").write_text("- aggregator=${oc.env:SEMVPR_TEST_SECRET}\n- seed=4\n")
    # Names with '|', a line break and HTML; class weights that are not numbers.
    bad = _metrics("none", 1, 10.0, aggregator="x|y\n<script>alert(1)</script>")
    bad["class_weights"] = {"road": "heavy"}
    _job(sweep, "filter=bad,seed=1", bad)
    text = write_report(sweep).read_text()
    assert "hunter2" not in text and "${oc.env:SEMVPR_TEST_SECRET}" in text
    assert "<script>" not in text and "x&#124;y &lt;script>alert(1)&lt;/script>" in text
    table = [ln for ln in text.splitlines() if ln.startswith("| vgg16 |")]
    assert all(ln.count(" | ") == table[0].count(" | ") for ln in table)  # no cell split or row broken
    # Images only under a recorded dataset root, whatever absolute path retrievals.json lists.
    private = _png(tmp_path / "private" / "secret.png", (1, 2, 3))
    loaded = load_sweep(sweep)
    assert loaded.image_path(str(private)) is None
    assert loaded.image_path(str(tmp_path / "data" / "q0.png")) == tmp_path / "data" / "q0.png"
    # All or none: a failure while making the report leaves the previous csv and md as they were.
    before = {name: (sweep / name).read_bytes() for name in ("results.csv", "results.md", "figure3.png")}
    monkeypatch.setattr(report, "_markdown", lambda *a: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        write_report(sweep)
    assert {name: (sweep / name).read_bytes() for name in before} == before
    assert not [p for p in sweep.iterdir() if p.name.startswith(".")]


def test_a_partial_report_has_the_finished_jobs_and_says_so(sweep: Path) -> None:
    """While a sweep runs, the table holds the jobs with a metrics.json (a started job's .hydra alone is not a
    crash yet), says it is partial, and draws no figure; the final report replaces it."""
    md = write_report(sweep, partial=True).read_text()
    finished = len(list(sweep.rglob("metrics.json")))
    assert md.splitlines()[2].startswith("**Partial: the sweep is still running.**")
    assert f"{finished} job(s) finished so far" in md and f"{finished} jobs, " in md
    assert not list(sweep.glob("*.png"))
    assert "mask2former,seed=3" not in md  # still running, not listed as failed
    assert {row["partial"] for row in _csv_rows(sweep).values()} == {"true"}  # the csv says so too
    final = write_report(sweep).read_text()
    assert "Partial" not in final and f"{finished + 1} jobs, " in final and list(sweep.glob("*.png"))
    # The hard crash left no metrics.json: the final report says the sweep is incomplete, and so does the csv.
    assert final.splitlines()[2].startswith(f"**Incomplete:** {finished + 1} jobs, ") and "1 did not finish" in final
    assert {row["partial"] for row in _csv_rows(sweep).values()} == {"true"}
    (sweep / "filter=mask2former,seed=3" / "metrics.json").write_text(json.dumps({"status": "failed", "error": "OOM"}))
    assert "Incomplete" not in write_report(sweep).read_text()
    assert {row["partial"] for row in _csv_rows(sweep).values()} == {"false"}


def _plan(sweep: Path, task: list[str], sweeper: str = BASIC_SWEEPER) -> None:
    """What a multirun's launch records before its first job (the report callback's ``on_multirun_start``)."""
    record = {"hydra": {"sweeper": {"_target_": sweeper, "params": None}, "overrides": {"task": task}}}
    record_plan(OmegaConf.create(record), sweep)


def test_a_stopped_sweeps_report_counts_every_job_it_was_given(tmp_path: Path) -> None:
    """Two of four jobs finished, one stopped mid-way, one never started: the report counts four, names the
    one that never started, and neither it nor the csv reads as complete."""
    sweep = tmp_path / "sweep"
    for seed, metrics in ((0, _metrics("none", 0, 50.0)), (1, _metrics("none", 1, 52.0)), (2, None)):
        job = _job(sweep, f"seed={seed}", metrics)
        OmegaConf.save(OmegaConf.create(["filter=none", f"seed={seed}"]), job / ".hydra" / "overrides.yaml")
    _plan(sweep, ["filter=none", "seed=0,1,2,3"])
    md = write_report(sweep).read_text()
    assert md.splitlines()[2].startswith("**Incomplete:** 4 jobs, 2 ok, 0 failed, 1 did not finish, 1 never started"), (
        md
    )
    assert "## Jobs not started\n\n- `filter=none seed=3`" in md
    assert {row["partial"] for row in _csv_rows(sweep).values()} == {"true"}
    # Another sweeper's plan is not known here: the folders are all there is.
    _plan(sweep, ["filter=none", "seed=0,1,2,3"], sweeper="hydra_plugins.optuna.OptunaSweeper")
    assert "3 jobs, 2 ok, 0 failed, 1 did not finish, 0 never started" in write_report(sweep).read_text()


def test_the_callback_rewrites_the_partial_table_after_each_job_of_a_multirun(
    sweep: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hydra = OmegaConf.create({"hydra": {"mode": RunMode.MULTIRUN, "sweep": {"dir": str(sweep)}}})
    monkeypatch.setattr(HydraConfig, "initialized", staticmethod(lambda: True))
    monkeypatch.setattr(HydraConfig, "get", staticmethod(lambda: hydra.hydra))
    ReportCallback().on_job_end(OmegaConf.create({}), None)
    assert "**Partial" in (sweep / "results.md").read_text()
    hydra.hydra.mode = RunMode.RUN  # a single run (or a DDP rank started as one) writes no sweep report
    (sweep / "results.md").unlink()
    ReportCallback().on_job_end(OmegaConf.create({}), None)
    assert not (sweep / "results.md").exists()


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("test/R@1", 150.0),
        ("test/R@5", -3),
        ("untrained/test/R@1", float("nan")),
        ("test/R@10", "90"),
        ("wall_time_s", float("inf")),
    ],
)
def test_a_jobs_numbers_out_of_range_make_it_a_failed_row_not_a_mean(tmp_path: Path, key: str, value: object) -> None:
    """A metrics.json is data: a recall outside [0, 100] (or not a number) or a wall time that is not finite
    makes its job a failed row saying which value, never a term of the row's mean."""
    sweep = tmp_path / "sweep"
    _job(sweep, "filter=none,seed=1", _metrics("none", 1, 40.0))
    _job(sweep, "filter=none,seed=2", {**_metrics("none", 2, 44.0), key: value})
    md = write_report(sweep).read_text()
    row = _csv_rows(sweep)["netvlad · none"]
    assert row["n"] == "1" and row["failed"] == "1" and float(row["R@1_mean"]) == pytest.approx(40.0)
    assert f"metrics.json's {key}=" in md


def test_each_table_reads_its_own_commands_jobs_and_names_the_other_table(sweep: Path) -> None:
    """An eval job beside the training runs (its Hydra record names it) was a failed training row, and each
    table read a folder of the other command's jobs as failed jobs of its own."""
    from semvpr.core.errors import SemvprError
    from semvpr.reporting.benchmarks_table import table_rows

    trained = sorted(job.name for job in load_sweep(sweep).jobs)
    evaluated = sweep / "eval-of-best"
    (evaluated / ".hydra").mkdir(parents=True)
    (evaluated / ".hydra" / "hydra.yaml").write_text("hydra:\n  job:\n    name: eval\n")
    (evaluated / "eval.json").write_text(json.dumps({"status": "ok"}))
    assert sorted(job.name for job in load_sweep(sweep).jobs) == trained
    assert len(table_rows(sweep)) == 1  # the eval job's row alone, not one failed row per training run
    evals = sweep.parent / "evals"
    evals.mkdir()
    evaluated.rename(evals / "0")
    with pytest.raises(SemvprError, match=rf"^{sweep} holds semvpr.train jobs, not semvpr.eval's; .*semvpr.report"):
        table_rows(sweep)
    with pytest.raises(
        SemvprError, match=r"holds semvpr.eval jobs, not semvpr.train's; their table: `python -m semvpr.evaltable"
    ):
        load_sweep(evals)


def test_the_terminal_shows_the_characters_a_report_escaped_and_no_control_characters() -> None:
    """The eval table's interval printed as ``&#91;`` in the terminal (an escape meant for rendered markdown)."""
    from semvpr.reporting.markdown import md_cell, terminal_text

    assert terminal_text([md_cell("−4.5 [−10.0, +1.0] a|b <c>"), "x\x1b[2Jy"]) == "−4.5 [−10.0, +1.0] a|b <c>\nx[2Jy"

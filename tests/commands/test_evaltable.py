"""One command evaluates a checkpoint on several datasets and writes one table beside published numbers."""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from semvpr.core.precision import lightning_precision
from semvpr.reporting.benchmarks_table import table_rows, write_table
from tests.helpers import (
    REPO,
    make_folder,
    object_array,
    same_images_as_lists,
    tiny_config,
    write_checkpoint,
    write_lists,
)


def test_multirun_over_datasets_and_roots_writes_one_table(tmp_path: Path) -> None:
    write_checkpoint(tiny_config(tmp_path, "filter=attention"), tmp_path / "tested.ckpt")
    root = make_folder(tmp_path / "city", n=4)
    db, q = same_images_as_lists(root)  # the same images as gsv-cities lists: query i is database image i again
    write_lists(tmp_path, "tiny_test", db, q, object_array([[i] for i in range(len(q))]))
    sweep = tmp_path / "sweep"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.eval",
            "-m",
            f"ckpt={tmp_path / 'tested.ckpt'}",
            "data=folder,gsv_npy",
            f"data.root={root},{tmp_path / 'missing'}",
            "++data.set=tiny_test",
            f"++data.gt_dir={tmp_path}",
            "data.image_size=[32,48]",
            "data.num_workers=0",
            f"paths.cache_dir={tmp_path / 'cache'}",
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    with (sweep / "results.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["data"], r["set"]) for r in rows if r["set"]] == [("folder", "city/test"), ("gsv_npy", "tiny_test")]
    for row in (r for r in rows if r["set"]):
        # Each query is its place's database image again: any model retrieves it first.
        assert (row["R@1"], row["R@20"], row["queries"], row["database"]) == ("100.0", "100.0", "4", "4")
        assert int(row["descriptor_dim"]) > 0 and float(row["wall_s"]) > 0
        assert row["precision"] == lightning_precision("bf16-mixed", "cpu")  # a semvpr checkpoint: the job's
        assert row["source"].startswith("measured: ") and "(sral, mask=none)" in row["source"]
    assert rows[2]["benchmark"] == "tiny_test"  # gsv_npy names its protocol after the set
    failed = [r for r in rows if not r["set"]]
    assert len(failed) == 2 and all(r["source"].startswith("failed: ") and "missing" in r["source"] for r in failed)
    assert [r["data"] for r in failed] == [f"data={d} data.root={tmp_path / 'missing'}" for d in ("folder", "gsv_npy")]
    ok = [f.parent for f in sweep.glob("*/eval.json") if json.loads(f.read_text())["status"] == "ok"]
    assert len(ok) == 2
    for job in ok:  # the per-query first-hit ranks beside each ok job's eval.json
        assert np.load(job / "ranks.npy").tolist() == [0, 0, 0, 0]
    md = (sweep / "results.md").read_text()
    assert md.count("| folder | city/test |") == 1 and "semvpr eval table:" in proc.stdout
    assert "Incomplete" not in md  # the four jobs it was given all ended, two of them failed
    assert "semvpr: job failed" in proc.stderr and "Traceback" not in proc.stderr
    # The jobs run side by side: each stage line names its job by number and overrides.
    staged = [ln for ln in proc.stderr.splitlines() if ln.startswith("semvpr: ") and "job failed" not in ln]
    named = [re.match(r"semvpr: \[#([0-3]) (\S+)\] ", ln) for ln in staged]
    assert staged and all(named), staged
    assert {m.group(1) for m in named if m} <= {"0", "1", "2", "3"} and all("data" in m.group(2) for m in named if m)


def _job(sweep: Path, num: int, result: dict) -> None:
    (sweep / str(num)).mkdir(parents=True)
    (sweep / str(num) / "eval.json").write_text(json.dumps(result))


def test_published_numbers_stand_beside_the_same_model_and_protocol(tmp_path: Path) -> None:
    base = {
        "status": "ok",
        "checkpoint": "m.ckpt",
        "aggregator": "netvlad",
        "mask": "none",
        "backbone": "vgg16",
        "model": "vgg16-netvlad",
        "database": 10000,
        "queries": 6816,
        "descriptor_dim": 32768,
        "wall_s": 12.5,
        **{f"test/R@{n}": 80.0 + n / 10 for n in (1, 5, 10, 20)},
    }
    _job(
        tmp_path,
        0,
        {**base, "data": "pitts30k", "set": "pitts30k-test", "benchmark": "pitts30k_test", "precision": "32-true"},
    )
    _job(tmp_path, 1, {**base, "data": "tokyo247", "set": "tokyo247-test", "benchmark": "tokyo247"})
    _job(
        tmp_path,
        2,
        {**base, "data": "pitts30k", "set": "pitts30k-test", "benchmark": "pitts30k_test", "model": "resnet50-gem"},
    )
    rows = table_rows(tmp_path)
    assert [r["data"] for r in rows] == ["pitts30k", "published", "published", "published", "tokyo247", "pitts30k"]
    # pytorch-NetVlad's README (vgg16): 85.2 / 94.8 / 97.0 on Pitts30k-test; R@20 not published.
    assert [rows[1][k] for k in ("R@1", "R@5", "R@10", "R@20")] == [85.2, 94.8, 97.0, ""]
    assert "pytorch-NetVlad" in rows[1]["source"] and rows[1]["benchmark"] == "pitts30k_test"
    md = write_table(tmp_path).read_text()
    assert (
        "| pitts30k | pitts30k-test | pitts30k_test | 80.10 | 80.50 | 81.00 | 82.00 | 6816 | 10000 | 32768 | 32-true "
        "| 12.50 |" in md
    )  # the precision eval.json records; an eval.json without one has an empty cell
    assert (
        "| tokyo247 | tokyo247-test | tokyo247 | 80.10 | 80.50 | 81.00 | 82.00 | 6816 | 10000 | 32768 |  | 12.50 |"
        in (md)
    )
    assert "| published | pitts30k-test | pitts30k_test | 85.20 | 94.80 | 97.00 |  |" in md
    assert (tmp_path / "results.csv").read_text().count("\n") == len(rows) + 1


def test_a_masked_row_gets_its_paired_r1_gain_over_the_same_checkpoint_without_a_mask(tmp_path: Path) -> None:
    base = {
        "status": "ok",
        "data": "gardens_point",
        "set": "gp day_left→night_right ±2",
        "aggregator": "sral",
        "backbone": "efficientnet_lite0",
        "model": "efficientnet_lite0-sral",
        "database": 200,
        "queries": 200,
        "descriptor_dim": 4096,
        "precision": "bf16-mixed",
        "wall_s": 1.0,
        **{f"test/R@{n}": 50.0 for n in (1, 5, 10, 20)},
    }
    rng = np.random.default_rng(3)
    none_ranks = rng.integers(0, 4, 200)  # rank 0: a hit at R@1
    mask_ranks = np.where(rng.random(200) < 0.3, 0, none_ranks)  # the mask turns some misses into hits
    jobs = [
        ({**base, "checkpoint": "a.ckpt", "mask": "none"}, none_ranks),
        ({**base, "checkpoint": "a.ckpt", "mask": "student"}, mask_ranks),
        ({**base, "checkpoint": "b.ckpt", "mask": "student"}, mask_ranks),  # b was never evaluated without
        ({**base, "checkpoint": "a.ckpt", "mask": "teacher"}, None),  # no ranks.npy: no paired gain
        ({**base, "checkpoint": "a.ckpt", "mask": "student", "precision": "32-true"}, mask_ranks),  # a's was bf16
    ]
    for num, (result, ranks) in enumerate(jobs):
        _job(tmp_path, num, {**result, **_recalls(ranks)} if ranks is not None else result)
        if ranks is not None:
            np.save(tmp_path / str(num) / "ranks.npy", ranks.astype(np.int32))
    rows = [r for r in table_rows(tmp_path) if r["data"] != "published"]
    expected = 100.0 * ((mask_ranks == 0).mean() - (none_ranks == 0).mean())
    assert expected > 5  # the fixture has a real gain
    match = re.fullmatch(r"([+−][\d.]+) \[([+−][\d.]+), ([+−][\d.]+)\]", rows[1]["R@1 vs no mask"])
    assert match, rows[1]["R@1 vs no mask"]
    value, low, high = (float(g.replace("−", "-")) for g in match.groups())
    assert value == round(expected, 1) and low < value < high and low > 0  # 30 % of misses flipped: significant
    assert [r.get("R@1 vs no mask", "") for r in (rows[0], rows[2], rows[3], rows[4])] == ["", "", "", ""]
    assert "R@1 vs no mask" in write_table(tmp_path).read_text()


def test_untrained_models_are_paired_by_model_not_by_their_shared_checkpoint_name(tmp_path: Path) -> None:
    """``ckpt=none aggregator=gem,netvlad mask=none,teacher``: every job's checkpoint is "none"; each masked row is
    paired with its own aggregator's unmasked job, never with the other aggregator's."""
    rng = np.random.default_rng(5)
    ranks = {name: rng.integers(0, 4, 100) for name in ("gem", "gem+mask", "netvlad", "netvlad+mask")}
    for num, name in enumerate(ranks):
        aggregator, _, masked = name.partition("+")
        result = {
            "status": "ok",
            "data": "folder",
            "set": "s",
            "checkpoint": "none",
            "aggregator": aggregator,
            "backbone": "b",
            "model": f"b-{aggregator}",
            "mask": "teacher" if masked else "none",
            "database": 50,
            "queries": 100,
            "descriptor_dim": 8,
            "wall_s": 1.0,
            **_recalls(ranks[name]),
        }
        _job(tmp_path, num, result)
        np.save(tmp_path / str(num) / "ranks.npy", ranks[name])
    rows = {r["source"]: r for r in table_rows(tmp_path) if r["data"] != "published"}
    for aggregator in ("gem", "netvlad"):
        row = next(r for s, r in rows.items() if f"b-{aggregator} ({aggregator}, mask=teacher" in s)
        gain = 100.0 * ((ranks[f"{aggregator}+mask"] == 0).mean() - (ranks[aggregator] == 0).mean())
        assert row["R@1 vs no mask"].startswith(f"{gain:+.1f}".replace("-", "−")), row["R@1 vs no mask"]


def _recalls(ranks: np.ndarray) -> dict[str, float]:
    """The recalls eval.json records for these first-hit ranks (-1: no positive, never a hit), 2 decimals."""
    return {
        f"test/R@{n}": round(100.0 * sum(0 <= r < n for r in ranks.tolist()) / len(ranks), 2) for n in (1, 5, 10, 20)
    }


def _masked_pair(tmp_path: Path, none_ranks: np.ndarray, mask_ranks: np.ndarray) -> dict:
    base = {
        "status": "ok",
        "data": "folder",
        "set": "s",
        "aggregator": "sral",
        "backbone": "b",
        "model": "m",
        "database": 50,
        "queries": len(none_ranks),
        "descriptor_dim": 8,
        "wall_s": 1.0,
        "checkpoint": "a.ckpt",
    }
    for num, (mask, ranks) in enumerate((("none", none_ranks), ("student", mask_ranks))):
        _job(tmp_path, num, {**base, "mask": mask, **_recalls(ranks)})
        np.save(tmp_path / str(num) / "ranks.npy", ranks)
    return base


def test_a_ranks_file_that_does_not_give_its_jobs_recalls_is_named_not_paired(tmp_path: Path) -> None:
    """ranks.npy feeds the paired interval: edited, truncated or swapped for another run's, it no longer gives
    the recalls its eval.json recorded, and the cell says so instead of an interval from other numbers."""
    rng = np.random.default_rng(0)
    none_ranks, mask_ranks = rng.integers(0, 30, 120), rng.integers(0, 30, 120)
    _masked_pair(tmp_path, none_ranks, mask_ranks)
    assert re.fullmatch(r"[+−][\d.]+ \[.*\]", table_rows(tmp_path)[1]["R@1 vs no mask"])
    edits = {
        "edited": (lambda p: np.save(p, np.zeros(120, np.int64)), "ranks.npy gives R@1 100.00, eval.json"),
        "truncated": (lambda p: p.write_bytes(p.read_bytes()[:150]), "unreadable ranks.npy (ValueError)"),
        "below -1": (lambda p: np.save(p, np.full(120, -7)), "ranks below -1"),
        "a folder": (lambda p: (p.unlink(), p.mkdir()), "unreadable ranks.npy (SemvprError)"),
    }
    for what, (edit, reason) in edits.items():
        edit(tmp_path / "1" / "ranks.npy")
        cell = table_rows(tmp_path)[1]["R@1 vs no mask"]
        assert cell.startswith("none: ") and reason in cell, (what, cell)
        path = tmp_path / "1" / "ranks.npy"
        path.rmdir() if path.is_dir() else path.unlink()
        np.save(path, mask_ranks)
    edits["edited"][0](tmp_path / "0" / "ranks.npy")  # the unmasked job's ranks are checked the same way
    assert table_rows(tmp_path)[1]["R@1 vs no mask"].startswith("none: the unmasked job: ranks.npy gives R@1")


def test_an_eval_json_with_values_out_of_range_is_a_failed_row(tmp_path: Path) -> None:
    base = _masked_pair(tmp_path, np.arange(10) % 3, np.arange(10) % 2)
    values = {
        "test/R@1": 150.0,
        "test/R@5": float("nan"),
        "queries": 0,
        "wall_s": float("inf"),
        "test/R@20": 0.5,
    }
    for key, value in values.items():
        (tmp_path / "2").mkdir(exist_ok=True)
        result = {**base, "mask": "teacher", **_recalls(np.arange(10) % 3), key: value}
        (tmp_path / "2" / "eval.json").write_text(json.dumps(result))
        row = table_rows(tmp_path)[-1]
        assert (
            row["source"].startswith("failed: eval.json")
            and key.removeprefix("test/") in row["source"]
            or (key == "test/R@20" and "fall as N grows" in row["source"])
        ), (key, row)


def test_a_stopped_evaluation_sweep_names_the_jobs_that_did_not_finish_or_never_started(tmp_path: Path) -> None:
    """Of three jobs given (recorded as the sweep starts), one finished, one started and left no eval.json, one never
    started: three rows, the table says it is incomplete, and no row holds the sweep's absolute path."""
    from omegaconf import OmegaConf

    from semvpr.config.runs import BASIC_SWEEPER, record_plan

    sweep = tmp_path / "sweep"
    task = ["ckpt=none", "aggregator=gem,netvlad,mixvpr"]
    hydra = {"sweeper": {"_target_": BASIC_SWEEPER, "params": None}, "overrides": {"task": task}}
    result = {"status": "ok", "data": "folder", "set": "s", "aggregator": "gem", "backbone": "b", "model": "m"}
    result |= {"database": 5, "queries": 4, "descriptor_dim": 8, "wall_s": 1.0, "checkpoint": "none", "mask": "none"}
    _job(sweep, 0, result | _recalls(np.zeros(4)))
    for num, aggregator in ((0, "gem"), (1, "netvlad")):
        (sweep / str(num) / ".hydra").mkdir(parents=True, exist_ok=True)
        OmegaConf.save(
            OmegaConf.create(["ckpt=none", f"aggregator={aggregator}"]), sweep / str(num) / ".hydra" / "overrides.yaml"
        )
    record_plan(OmegaConf.create({"hydra": hydra}), sweep)
    rows = table_rows(sweep)
    assert [r["source"] for r in rows[1:]] == ["failed: did not finish: no eval.json", "not started"]
    assert [r["data"] for r in rows[1:]] == ["ckpt=none aggregator=netvlad", "ckpt=none aggregator=mixvpr"]
    md = write_table(sweep).read_text()
    assert "**Incomplete:** 1 job(s) did not finish and 1 never started" in md and str(sweep) not in md
    (sweep / "1" / "eval.json").write_text("{not json")
    assert str(sweep) not in write_table(sweep).read_text()

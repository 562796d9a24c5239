"""End-to-end training jobs on the tiny SynthCity preset."""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from PIL import Image

from semvpr import train
from semvpr.config.build import build_aggregator, build_backbone
from semvpr.config.plan import settings_of
from semvpr.core.checkpoint import confine_callback_state
from semvpr.core.errors import SemvprError
from semvpr.train import run_job
from tests.helpers import CONF_DIR, REPO, config, tiny_config


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One artifact cache for the whole session: SynthCity, teacher and labels are built once."""
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="session")
def trained_run(cache_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A complete tiny filter=none job (2 epochs)."""
    run_dir = tmp_path_factory.mktemp("run")
    run_job(tiny_config(cache_dir, "filter=none", "trainer.max_epochs=2"), run_dir)
    return run_dir


@pytest.mark.parametrize(
    "filter_name,backbone",
    [
        ("none", "vgg16"),
        ("attention", "vgg16"),
        ("unet", "vgg16"),
        ("mask2former", "vgg16"),
        ("oracle", "vgg16"),
        ("unet", "resnet50"),
    ],
)
def test_fast_dev_run_each_filter(cache_dir: Path, tmp_path: Path, filter_name: str, backbone: str) -> None:
    cfg = tiny_config(cache_dir, f"filter={filter_name}", f"backbone={backbone}", "+trainer.fast_dev_run=true")
    metrics = run_job(cfg, tmp_path)
    assert metrics["filter"] == filter_name and metrics["backbone"] == backbone
    # Recall re-derived from the written top-5 lists (tiny has 24 test queries: all of them are written).
    queries = json.loads((tmp_path / "retrievals.json").read_text())["queries"]
    assert len(queries) == 24
    for n in (1, 5):
        hits = [any(m["correct"] for m in q["topk"][:n]) for q in queries]
        assert metrics[f"test/R@{n}"] == pytest.approx(100.0 * sum(hits) / len(hits))
    maps = np.load(tmp_path / "maps.npz")
    if filter_name != "none":
        attention = maps["attention"]
        assert attention.min() >= 0.0 and attention.max() <= 1.0 + 1e-5
    expected_mask = {"unet": "student", "mask2former": "teacher", "oracle": "oracle"}.get(filter_name)
    if expected_mask:
        assert set(np.unique(maps[expected_mask])) <= {0.0, 1.0}


# Descriptor sizes as set in their yaml (GeM: its CosPlace head's fc_dim).
@pytest.mark.parametrize("aggregator,dim", [("gem", 512), ("mixvpr", 2048), ("salad", 256 + 8 * 64), ("boq", 128 * 16)])
def test_fast_dev_run_each_aggregator_with_a_mask(
    cache_dir: Path, tmp_path: Path, aggregator: str, dim: int | None
) -> None:
    cfg = tiny_config(
        cache_dir, f"aggregator={aggregator}", "mask=oracle", "model.pca_dim=8", "+trainer.fast_dev_run=true"
    )
    backbone = build_backbone(cfg.backbone, cfg.seed)
    assert build_aggregator(settings_of(cfg), backbone).output_dim == (dim or backbone.out_channels)
    metrics = run_job(cfg, tmp_path)
    # PCA whitening works on any aggregator's descriptor
    assert (metrics["aggregator"], metrics["mask"], metrics["descriptor_dim"]) == (aggregator, "oracle", 8)
    assert metrics["aggregator_init"] == {"init": "none"} and 0.0 <= metrics["test/R@1"] <= 100.0
    maps = np.load(tmp_path / "maps.npz")
    assert "attention" not in maps.files and set(np.unique(maps["oracle"])) <= {0.0, 1.0}


def test_preset_and_explicit_choices_compose() -> None:
    unet = config("filter=unet")
    assert (unet.aggregator.name, unet.mask.name, unet.mask.weights) == ("sral", "student", "binary")
    learned = config("filter=mask2former", "filter.weights=learned")
    assert (learned.aggregator.name, learned.mask.name, learned.mask.weights) == ("sral", "teacher", "learned")
    # an explicit group choice wins over the preset's
    mixed = config("filter=unet", "aggregator=gem")
    assert (mixed.aggregator.name, mixed.mask.name) == ("gem", "student")
    plain = config("aggregator=salad", "mask=teacher", "mask.weights=learned")
    assert (plain.aggregator.name, plain.mask.name, plain.mask.weights) == ("salad", "teacher", "learned")
    assert (config().aggregator.name, config().mask.name) == ("netvlad", "none")


def test_run_writes_metrics_logs_and_checkpoints(trained_run: Path) -> None:
    metrics = json.loads((trained_run / "metrics.json").read_text())
    assert metrics["status"] == "ok" and metrics["backbone"] == "efficientnet_lite0" and metrics["seed"] == 0
    assert metrics["backbone_weights"] == "imagenet"  # the report marks "none" and "file" in its backbone column
    assert [metrics["recalls"][str(n)] for n in (1, 5, 10, 20)] == [metrics[f"test/R@{n}"] for n in (1, 5, 10, 20)]
    # SynthCity test queries all have positives: both denominators agree.
    assert metrics["test_queries_without_positives"] == 0
    assert all(metrics[f"test/R@{n}_pos"] == metrics[f"test/R@{n}"] for n in (1, 5, 10, 20))
    assert (trained_run / "checkpoints" / "last.ckpt").is_file()
    assert (trained_run / "checkpoints" / "best.ckpt").is_file()
    assert metrics["checkpoint"] == str(trained_run / "checkpoints" / "tested.ckpt")
    assert list((trained_run / "tensorboard").rglob("events.out.tfevents.*"))
    # TensorBoard holds the learning rate per epoch and hp_metric set to the test R@1 (it stayed -1).
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events,) = {p.parent for p in (trained_run / "tensorboard").rglob("events.out.tfevents.*")}
    scalars = EventAccumulator(str(events)).Reload().Tags()["scalars"]
    accumulated = EventAccumulator(str(events)).Reload()
    assert any(tag.startswith("lr-") for tag in scalars) and "val/R@1" in scalars, scalars
    assert accumulated.Scalars("hp_metric")[-1].value == pytest.approx(metrics["test/R@1"], abs=1e-4)
    # After each validation, four validation queries drawn with their retrievals (reporting.tensorboard).
    from semvpr.reporting.prediction_images import CAPTION, FRAME, GAP, THUMB_H

    (retrievals,) = accumulated.Tags()["images"]
    drawn = accumulated.Images(retrievals)
    assert retrievals == "val/retrievals" and [e.step for e in drawn] == [0, 1], drawn
    tile = round(THUMB_H * 80 / 64) + 2 * FRAME  # tiny's images are 64 x 80
    assert (drawn[-1].height, drawn[-1].width) == (4 * (THUMB_H + 2 * FRAME + CAPTION), 5 * tile + 4 * GAP)
    shown = Image.open(io.BytesIO(drawn[-1].encoded_image_string))  # a JPEG: add_image's PNG costs 40x more
    assert shown.format == "JPEG" and shown.size == (drawn[-1].width, drawn[-1].height)
    # The tested weights' epoch is the first with the best val/R@5 in the run's own CSV log (1-based).
    (log,) = list((trained_run / "csv").rglob("metrics.csv"))
    rows = list(csv.DictReader(log.read_text().splitlines()))
    val = [(int(r["epoch"]) + 1, float(r["val/R@5"])) for r in rows if r.get("val/R@5")]
    assert len(val) == 2 and metrics["best/epoch"] == max(val, key=lambda e: (e[1], -e[0]))[0]
    assert metrics["best/val/R@5"] == pytest.approx(max(r5 for _, r5 in val))
    retrievals = json.loads((trained_run / "retrievals.json").read_text())
    queries = [q["query"] for q in retrievals["queries"]]
    all_queries = sorted(p.name for p in Path(queries[0]).parent.iterdir())
    assert len(set(queries)) == len(queries) == min(48, len(all_queries))  # tiny has 24 queries
    assert {Path(queries[0]).name, Path(queries[-1]).name} == {all_queries[0], all_queries[-1]}
    assert all(len(q["topk"]) == 5 for q in retrievals["queries"])


@pytest.mark.slow
def test_training_beats_kmeans_only_model(tmp_path: Path) -> None:
    # The tiny preset's 24 test queries are too few to resolve the gain; this uses the default
    # preset (a few minutes on 2 cores; measured 21.9 -> 29.9 R@1 for seed 0 on SynthCity v3).
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"paths.cache_dir={tmp_path / 'cache'}", "filter=none"])
    metrics = run_job(cfg, tmp_path / "run")
    assert metrics["test/R@1"] > metrics["untrained/test/R@1"], metrics


@pytest.mark.reproducibility
def test_resumed_run_ends_as_the_uninterrupted_one(cache_dir: Path, trained_run: Path, tmp_path: Path) -> None:
    # Stopped after epoch 1 of 2 (what a kill leaves: last.ckpt of epoch 1), then resumed.
    run_dir = tmp_path / "run"
    run_job(tiny_config(cache_dir, "filter=none", "trainer.max_epochs=1"), run_dir)
    first = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True)
    resumed = run_job(tiny_config(cache_dir, "filter=none", "trainer.max_epochs=2", "ckpt_path=last"), run_dir)
    last = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True)
    reference = torch.load(trained_run / "checkpoints" / "last.ckpt", weights_only=True)
    assert first["epoch"] == 0 and (last["epoch"], last["global_step"]) == (
        reference["epoch"],
        reference["global_step"],
    )
    # The resumed run trained only the remaining epoch: its own log starts at epoch 1.
    resumed_log = sorted((run_dir / "csv").rglob("metrics.csv"))[-1].read_text().splitlines()
    assert all(line.split(",")[0] != "0" for line in resumed_log[1:])
    # Mining RNG (per epoch), negative cache and optimizer state travel: same numbers, same weights.
    uninterrupted = json.loads((trained_run / "metrics.json").read_text())
    assert resumed["recalls"] == uninterrupted["recalls"]
    weights = [
        torch.load(m, weights_only=True)["state_dict"] for m in (resumed["checkpoint"], uninterrupted["checkpoint"])
    ]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_resume_never_touches_a_file_named_by_a_tampered_checkpoint(cache_dir: Path, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    run_job(tiny_config(cache_dir, "filter=none", "trainer.max_epochs=1"), run_dir)
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    last = run_dir / "checkpoints" / "last.ckpt"
    ckpt = torch.load(last, weights_only=True)
    escaping = str(run_dir / "checkpoints" / ".." / ".." / "victim.txt")  # textually under checkpoints/
    callbacks = [state for name, state in ckpt["callbacks"].items() if name.startswith("RunCheckpoint")]
    assert len(callbacks) == 2
    for state in callbacks:
        state.update(
            best_model_path=escaping,
            kth_best_model_path=escaping,
            last_model_path=escaping,
            best_k_models={escaping: torch.tensor(-1.0)},
            best_model_score=torch.tensor(-1.0),
        )
    torch.save(ckpt, last)
    resumed = run_job(tiny_config(cache_dir, "filter=none", "trainer.max_epochs=2", "ckpt_path=last"), run_dir)
    assert victim.read_text() == "keep"
    assert resumed["status"] == "ok" and (run_dir / "checkpoints" / "best.ckpt").is_file()


def test_a_moved_run_directory_resumes_as_it_would_in_place(cache_dir: Path, tmp_path: Path) -> None:
    # A run stopped after epoch 1 of 2, its directory then moved (copied off a scratch disk).
    written_in, moved = tmp_path / "scratch" / "run", tmp_path / "home" / "run"
    run_job(tiny_config(cache_dir, "filter=none", "trainer.max_epochs=1"), written_in)
    shutil.move(written_in, moved)
    epoch_one = torch.load(moved / "checkpoints" / "best.ckpt", weights_only=True)
    metrics = run_job(tiny_config(cache_dir, "filter=none", "trainer.max_epochs=2", "ckpt_path=last"), moved)
    second = torch.load(moved / "checkpoints" / "last.ckpt", weights_only=True)
    best_state = next(s for name, s in second["callbacks"].items() if "'monitor': 'val/R@5'" in name)
    assert Path(best_state["best_model_path"]) == moved / "checkpoints" / "best.ckpt"
    # The tested weights are those of the epoch the metrics name as the best (on val R@5).
    tested = torch.load(metrics["checkpoint"], weights_only=True)["state_dict"]
    expected = {1: epoch_one, 2: second}[metrics["best/epoch"]]["state_dict"]
    assert tested.keys() == expected.keys() and all(torch.equal(tested[k], expected[k]) for k in expected)
    assert metrics["best/val/R@5"] == pytest.approx(float(best_state["best_model_score"]))


def test_a_moved_runs_checkpoint_state_reads_its_files_where_they_are_now(tmp_path: Path) -> None:
    here = tmp_path / "home" / "checkpoints"
    here.mkdir(parents=True)
    (here / "best.ckpt").touch()
    (here / "last.ckpt").touch()
    old = "/scratch/job/checkpoints"
    state = {
        "dirpath": old,
        "best_model_path": f"{old}/best.ckpt",
        "best_model_score": torch.tensor(90.0),
        "kth_best_model_path": f"{old}/best.ckpt",
        "last_model_path": f"{old}/gone.ckpt",
        "best_k_models": {f"{old}/best.ckpt": torch.tensor(90.0), "/elsewhere/best.ckpt": torch.tensor(99.0)},
    }
    own = confine_callback_state(state, here, own_file=True)
    assert own["dirpath"] == str(here) and own["best_model_path"] == str(here / "best.ckpt")
    assert float(own["best_model_score"]) == 90.0 and own["last_model_path"] == ""  # not there: forgotten
    assert list(own["best_k_models"]) == [str(here / "best.ckpt")]
    # Read from another run's file, the state names nothing here.
    foreign = confine_callback_state(state, here)
    assert foreign["best_model_path"] == "" and foreign["best_model_score"] is None and foreign["best_k_models"] == {}


def test_nan_loss_stops_and_keeps_last_good_checkpoint(
    cache_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from semvpr.retrieval import losses

    last = tmp_path / "checkpoints" / "last.ckpt"
    original = losses.triplet_loss

    def nan_after_first_epoch(*args):  # type: ignore[no-untyped-def]
        loss = original(*args)
        return loss * float("nan") if last.exists() else loss

    monkeypatch.setattr(losses, "triplet_loss", nan_after_first_epoch)
    with pytest.raises(SemvprError, match="loss became nan"):
        run_job(tiny_config(cache_dir, "filter=none", "trainer.max_epochs=3"), tmp_path)
    assert torch.load(last, weights_only=True)["epoch"] == 0
    assert json.loads((tmp_path / "metrics.json").read_text())["status"] == "failed"


def test_the_loss_watch_reads_the_losses_every_n_steps_and_names_the_first_bad_one() -> None:
    """The per-step `bool(isfinite(loss))` made the host wait for the device at every step: the watch keeps the
    losses as tensors and reads them every n, naming the first non-finite one's epoch and step."""
    from semvpr.retrieval.retriever import LossWatch

    watch = LossWatch(every=4)
    for step, value in enumerate([1.0, float("inf"), float("nan")]):
        watch.note(torch.tensor(value), 2, 10 + step)  # not read yet: no raise
    with pytest.raises(SemvprError, match="loss became inf at epoch 2 step 11;"):
        watch.note(torch.tensor(0.5), 2, 13)
    assert watch.losses == []  # read once, then forgotten
    watch.note(torch.tensor(float("nan")), 3, 14)
    with pytest.raises(SemvprError, match="nan at epoch 3 step 14"):
        watch.check()  # as before a validation or a checkpoint
    watch.check()  # nothing left to read


def test_failed_job_in_sweep_is_recorded_not_raised(cache_dir: Path, tmp_path: Path) -> None:
    metrics = run_job(tiny_config(cache_dir, "model.num_clusters=0"), tmp_path, multirun=True)
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["status"] == written["status"] == "failed"
    assert "model.num_clusters=0" in written["error"]


def test_signal_stops_the_sweep_instead_of_recording_a_failure(tmp_path: Path, monkeypatch) -> None:
    def killed(cfg, run_dir):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler interrupts this sleep
        raise AssertionError("SIGTERM was ignored")

    monkeypatch.setattr(train, "fit_and_test", killed)
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(train.Interrupted, match="SIGTERM"):
        run_job(OmegaConf.create({"seed": 0}), tmp_path, multirun=True)
    assert not (tmp_path / "metrics.json").exists()
    assert signal.getsignal(signal.SIGTERM) is before  # handler restored


def test_a_signal_during_training_is_one_line_that_says_how_to_resume(tmp_path: Path) -> None:
    """SIGTERM lands wherever the job is (inside Lightning's backward, say): the command prints one line with
    the resume command, not that traceback, exits 2 and leaves no metrics.json, only the checkpoint to resume.
    Every checkpoint is staged inside the run directory: nothing is written to $TMPDIR, mid-save or not."""
    run, tmpdir = tmp_path / "run", tmp_path / "tmpdir"
    tmpdir.mkdir()
    args = [
        "experiment=tiny",
        "filter=none",
        "threads=1",
        "trainer.max_epochs=400",
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"hydra.run.dir={run}",
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "1", "TMPDIR": str(tmpdir)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "semvpr.train", *args], cwd=tmp_path, stderr=subprocess.PIPE, text=True, env=env
    )
    assert proc.stderr is not None
    lines = []
    for line in proc.stderr:  # wait until a few epochs (and so last.ckpt) exist
        lines.append(line)
        if "epoch 3/400" in line:
            break
    proc.send_signal(signal.SIGTERM)
    rest = proc.stderr.read()
    assert proc.wait(timeout=600) == 2, rest[-3000:]
    tail = [ln for ln in rest.splitlines() if ln.strip() and not ln.startswith("semvpr: retriever: epoch")]
    assert tail == [
        f"semvpr: error: stopped by SIGTERM; resume it: python -m semvpr.train ckpt_path=last hydra.run.dir={run}"
    ], rest[-3000:]
    assert not (run / "metrics.json").exists() and (run / "checkpoints" / "last.ckpt").is_file()
    # torch makes its compile cache folder (empty) in $TMPDIR as lightning imports it; nothing else is there.
    assert [p for p in tmpdir.rglob("*") if not p.name.startswith("torchinductor_")] == []


def _eval(cache_dir: Path, *overrides: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.eval",
            "experiment=tiny",
            f"paths.cache_dir={cache_dir}",
            f"hydra.run.dir={cache_dir.parent / 'eval'}",
            *overrides,
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_eval_reproduces_test_recall(cache_dir: Path, trained_run: Path) -> None:
    metrics = json.loads((trained_run / "metrics.json").read_text())
    proc = _eval(cache_dir, f"ckpt={metrics['checkpoint']}")
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["test/R@1"] == pytest.approx(metrics["test/R@1"], abs=0.01)
    # The last line names the job's folder first, as train's does, and eval.json every file written beside it.
    run_dir = cache_dir.parent / "eval"
    assert next(iter(result)) == "run_dir" and result["run_dir"] == str(run_dir)
    recorded = json.loads((run_dir / "eval.json").read_text())
    assert recorded["files"] == ["ranks.npy", "hits.npz"] and all((run_dir / f).is_file() for f in recorded["files"])
    # The job's log holds its stage lines (it was created empty): what the console showed.
    stages = [ln for ln in proc.stderr.splitlines() if ln.startswith("semvpr: ")]
    assert stages and (run_dir / "eval.log").read_text().splitlines()[-len(stages) :] == stages
    # Run alone, the command has no job beside it: the cores are its own, as they are the in-process job's
    # (its config names the sweep launcher all the same).
    assert result["threads"]["processes"] == metrics["threads"]["processes"] == 1
    assert result["threads"]["share"] == metrics["threads"]["share"]


def test_eval_rejects_checkpoint_of_another_backbone(cache_dir: Path, trained_run: Path) -> None:
    proc = _eval(cache_dir, f"ckpt={trained_run / 'checkpoints' / 'best.ckpt'}", "backbone=resnet50")
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "backbone=efficientnet_lite0" in proc.stderr
    missing = _eval(cache_dir, f"ckpt={trained_run / 'nope.ckpt'}")
    assert missing.returncode == 2 and "not found" in missing.stderr


def test_pca_whitening_is_fitted_and_travels_with_the_checkpoint(cache_dir: Path, tmp_path: Path) -> None:
    metrics = run_job(tiny_config(cache_dir, "filter=none", "model.pca_dim=16"), tmp_path)
    state = torch.load(metrics["checkpoint"], weights_only=True)["state_dict"]
    assert state["whitening.projection"].shape == (16, 8 * 112) and bool(state["whitening_fitted"])
    proc = _eval(cache_dir, f"ckpt={metrics['checkpoint']}")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1])["test/R@1"] == pytest.approx(metrics["test/R@1"], abs=0.01)


def test_localize_matches_the_cached_pipeline(cache_dir: Path, trained_run: Path, tmp_path: Path) -> None:
    retrievals = json.loads((trained_run / "retrievals.json").read_text())["queries"][:3]
    queries = tmp_path / "queries"
    queries.mkdir()
    for i, item in enumerate(retrievals):
        (queries / f"q{i}.jpg").write_bytes(Path(item["query"]).read_bytes())
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.localize",
            "experiment=tiny",
            f"paths.cache_dir={cache_dir}",
            f"ckpt={trained_run / 'checkpoints' / 'tested.ckpt'}",
            f"queries={queries}",
            "top_k=3",
            f"hydra.run.dir={tmp_path / 'out'}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    results = json.loads((tmp_path / "out" / "localize.json").read_text())
    # Images through the full pipeline retrieve what the cached-feature evaluation retrieved.
    assert [r["matches"][0]["path"] for r in results] == [item["topk"][0]["path"] for item in retrievals]
    empty = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.localize",
            "experiment=tiny",
            f"paths.cache_dir={cache_dir}",
            f"ckpt={trained_run / 'checkpoints' / 'tested.ckpt'}",
            f"queries={tmp_path / 'none'}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert empty.returncode == 2 and "does not exist" in empty.stderr


def _count_trunk_passes(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The sides of every image pass that writes trunk features, appended as they happen."""
    from semvpr.retrieval import features

    passes: list[str] = []
    extract = features._extract

    def counted(*args, **kwargs):
        if args[6]:  # frozen outputs written (trunk, skips)
            passes.append(args[-1])
        return extract(*args, **kwargs)

    monkeypatch.setattr(features, "_extract", counted)
    return passes


@pytest.mark.reproducibility
def test_same_numbers_whether_artifacts_are_built_cached_or_streamed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    passes = _count_trunk_passes(monkeypatch)
    cfg = tiny_config(tmp_path / "cache", "filter=none", "trainer.max_epochs=2")
    built = run_job(cfg, tmp_path / "built")  # SynthCity and the trunk features
    assert len(passes) == 6  # train/val/test x database/queries
    cached = run_job(cfg, tmp_path / "cached")
    streamed = run_job(
        tiny_config(tmp_path / "cache", "filter=none", "trainer.max_epochs=2", "features.storage=stream"),
        tmp_path / "streamed",
    )
    # A streamed store is read by loader workers (kept from one sub-epoch to the next).
    workers = run_job(
        tiny_config(
            tmp_path / "cache", "filter=none", "trainer.max_epochs=2", "features.storage=stream", "data.num_workers=1"
        ),
        tmp_path / "workers",
    )
    assert len(passes) == 6  # the cached job read them, the streamed ones wrote none
    assert (built["feature_storage"], cached["feature_storage"], streamed["feature_storage"]) == (
        "ram",
        "ram",
        "stream",
    )
    _assert_same_run(built, cached, streamed, workers)


@pytest.mark.reproducibility
def test_a_randomly_initialised_aggregator_is_the_same_whether_the_student_was_built_or_cached(tmp_path: Path) -> None:
    """Training the student re-seeds the global RNGs; the aggregator's random layers (GeM's head) must not
    depend on whether this job trained it or read it from the cache."""
    cfg = tiny_config(tmp_path / "cache", "aggregator=gem", "mask=student", "trainer.max_epochs=1")
    built = run_job(cfg, tmp_path / "built")
    assert built["timings"]["student_s"] > 0
    cached = run_job(cfg, tmp_path / "cached")
    assert built["untrained/test/R@1"] == cached["untrained/test/R@1"]
    first, again = (
        torch.load(tmp_path / d / "checkpoints" / "tested.ckpt", weights_only=True) for d in ("built", "cached")
    )
    assert all(torch.equal(first["state_dict"][k], again["state_dict"][k]) for k in first["state_dict"])


@pytest.mark.parametrize("weights,passes_per_seed", [("imagenet", [6, 0]), ("none", [6, 6])])
def test_seeds_share_the_pretrained_trunk_pass(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, weights: str, passes_per_seed: list[int]
) -> None:
    # A frozen ImageNet trunk is the same network for every seed: one pass per image for a seed sweep;
    # a random-init trunk is another network per seed.
    passes = _count_trunk_passes(monkeypatch)
    counts = []
    for seed in (0, 1):
        before = len(passes)
        run_job(
            tiny_config(
                tmp_path / "cache",
                "filter=none",
                f"seed={seed}",
                f"backbone.weights={weights}",
                "+trainer.fast_dev_run=true",
            ),
            tmp_path / f"seed{seed}",
        )
        counts.append(len(passes) - before)
    assert counts == passes_per_seed
    assert len(list((tmp_path / "cache").glob("trunk-*"))) == (3 if weights == "imagenet" else 6)  # one per split


@pytest.mark.reproducibility
@pytest.mark.slow
def test_same_numbers_whether_semantic_artifacts_are_built_or_cached(tmp_path: Path) -> None:
    cfg = tiny_config(tmp_path / "cache", "filter=unet", "trainer.max_epochs=2")
    built = run_job(cfg, tmp_path / "built")  # SynthCity, teacher, pseudo-labels, student, trunk, masks
    cached = run_job(cfg, tmp_path / "cached")
    # Everything built again from nothing, in another cache: the builds themselves are deterministic.
    rebuilt = run_job(tiny_config(tmp_path / "cache2", "filter=unet", "trainer.max_epochs=2"), tmp_path / "rebuilt")
    assert {"data_s", "teacher_s", "labels_s", "student_s", "features_s", "fit_s"} <= set(built["timings"])
    # Each semantic stage is paid once: the second job reads teacher, labels and student from the cache.
    assert all(cached["timings"][k] < built["timings"][k] for k in ("semantic_s", "teacher_s", "labels_s", "student_s"))
    _assert_same_run(built, cached, rebuilt)


def _assert_same_run(first: dict, *others: dict) -> None:
    """Same recalls, same best validation score, bit-identical tested weights."""
    weights = [torch.load(run["checkpoint"], weights_only=True)["state_dict"] for run in (first, *others)]
    for run, w in zip(others, weights[1:]):
        assert run["recalls"] == first["recalls"] and run["best/val/R@5"] == first["best/val/R@5"]
        assert all(torch.equal(weights[0][k], w[k]) for k in weights[0])


@pytest.mark.parametrize("storage,unet_passes", [("ram", 0), ("disk", 6)])
def test_a_sweeps_jobs_share_the_trunk_pass_of_a_small_set(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, storage: str, unet_passes: int
) -> None:
    # A small set's first pass (here filter=none's) keeps what the student and the linked teacher read, so the
    # filter=unet job after it passes no image through the trunk; a set held on disk keeps only its own levels.
    passes = _count_trunk_passes(monkeypatch)

    def job(cache: str, name: str) -> tuple[dict, int]:
        before = len(passes)
        cfg = tiny_config(tmp_path / cache, f"filter={name}", f"features.storage={storage}", "trainer.max_epochs=1")
        return run_job(cfg, tmp_path / cache / name), len(passes) - before

    assert job("shared", "none")[1] == 6  # train/val/test x database/queries
    unet, made = job("shared", "unet")
    assert made == unet_passes
    assert len(list((tmp_path / "shared").glob("skips-*"))) == 6  # levels 1 and 2 (the trunk is 3) x 3 splits
    if storage == "ram":
        # The same job on its own makes its passes and gets the same run, bit for bit.
        alone, made = job("alone", "unet")
        assert made == 6
        _assert_same_run(unet, alone)


def test_a_signal_that_surfaces_as_a_librarys_error_is_a_stop_not_a_failure(tmp_path: Path, monkeypatch) -> None:
    """A signal landing inside a library (torch writing a checkpoint) can come out as that library's own
    error: the job is stopped, not recorded as failed with that error."""

    def killed_mid_save(cfg, run_dir):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except BaseException as err:  # what torch's writer does to the stop
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos") from err
        raise AssertionError("SIGINT was ignored")

    monkeypatch.setattr(train, "fit_and_test", killed_mid_save)
    with pytest.raises(train.Interrupted, match="SIGINT"):
        run_job(OmegaConf.create({"seed": 0}), tmp_path, multirun=True)
    assert not (tmp_path / "metrics.json").exists()
    # The next job of the process starts afresh: a failure of its own is not taken for that stop.
    from semvpr.core import stops

    assert stops.received_stop() is not None
    for sig, handler in stops.stop_on_signals().items():
        signal.signal(sig, handler)
    assert stops.received_stop() is None


def test_a_job_run_again_in_its_directory_leaves_only_its_own_checkpoints(cache_dir: Path, tmp_path: Path) -> None:
    """Lightning versioned the best checkpoint of a second job in one directory (best-v1.ckpt), leaving the first
    job's best.ckpt, the file the docs and experiments evaluate, beside it."""
    run_job(tiny_config(cache_dir, "filter=none", "seed=1"), tmp_path)
    first = torch.load(tmp_path / "checkpoints" / "best.ckpt", weights_only=True)["state_dict"]
    metrics = run_job(tiny_config(cache_dir, "filter=none", "seed=2"), tmp_path)
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["best.ckpt", "last.ckpt", "tested.ckpt"]
    second = torch.load(tmp_path / "checkpoints" / "best.ckpt", weights_only=True)["state_dict"]
    assert any(not torch.equal(first[k], second[k]) for k in first)
    assert json.loads((tmp_path / "metrics.json").read_text())["seed"] == metrics["seed"] == 2

"""recipe=gsv: GSV-Cities' P places × K images batches, the multi-similarity miner and loss of
pytorch-metric-learning, the GSV-Cities layout reader, SynthCity's training places, and whole jobs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from pytorch_metric_learning import distances, losses, miners

from semvpr.config.build import build_backbone, build_retriever
from semvpr.config.plan import settings_of
from semvpr.core.errors import SemvprError
from semvpr.data.gsv_cities import read_gsv_cities
from semvpr.data.places import PlaceIds, PlaceSet, read_utm_folder
from semvpr.data.synthcity import ensure_synthcity, read_split
from semvpr.retrieval.losses import MultiSimilarity
from semvpr.retrieval.places import PlaceBatching, epoch_batches, training_places
from semvpr.train import run_job
from tests.helpers import GSV_CITIES, REPO, config, gsv_name, gsv_row, tiny_config, write_gsv_cities

K = 4


@pytest.fixture(scope="session")
def gsv_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One artifact cache for this module's jobs: tiny SynthCity and its traversals are drawn once."""
    return tmp_path_factory.mktemp("gsv-cache")


# ----------------------------------------------------------------------------------- place batches
def _line_of_places(counts: list[int], groups: list[int], step_m: float = 5.0) -> PlaceSet:
    """Places along a line, ``step_m`` apart (a group per 1 km line), with ``counts[p]`` images each, the
    first image of each place a database image and the others queries."""
    db, q, db_utm, q_utm, db_ids, q_ids = [], [], [], [], [], []
    for p, n in enumerate(counts):
        utm = (step_m * p, 1000.0 * groups[p])
        db.append(Path(f"/x/db/{p}.jpg")), db_utm.append(utm), db_ids.append(p)
        for k in range(1, n):
            q.append(Path(f"/x/q/{p}_{k}.jpg")), q_utm.append(utm), q_ids.append(p)
    return PlaceSet(
        "line", tuple(db), tuple(q), np.array(db_utm), np.array(q_utm), place_ids=PlaceIds(db_ids, q_ids, groups)
    )


def test_place_batches_hold_p_places_of_k_images_each() -> None:
    # 3 groups (routes) of 40 places 5 m apart; every 7th place has fewer than K images.
    groups = [g for g in range(3) for _ in range(40)]
    counts = [2 if p % 7 == 3 else 4 + p % 3 for p in range(len(groups))]
    places = _line_of_places(counts, groups)
    train = training_places(places, K)
    assert train.left_out == sum(c < K for c in counts)
    batching = PlaceBatching(places_per_batch=6, images_per_place=K, separation=25.0, seed=3)
    batches = epoch_batches(train, batching, epoch=0)
    place_of = np.concatenate([places.place_ids.db, places.place_ids.q])
    utm = np.concatenate([places.db_utm, places.q_utm])
    seen: list[int] = []
    for batch in batches:
        rows = np.array(batch).reshape(-1, K)  # place-major: row p*K + k is image k of place p
        assert 2 <= len(rows) <= 6
        for place_rows in rows:
            assert len(set(place_rows)) == K and len(set(place_of[place_rows])) == 1  # K distinct images of one place
        # The labels a batch carries are the places of its rows.
        assert all(len(set(train.labels[r])) == 1 for r in rows)
        assert len({train.labels[r[0]] for r in rows}) == len(rows)
        firsts = utm[rows[:, 0]]
        gaps = np.hypot(*(firsts[:, None] - firsts[None]).transpose(2, 0, 1))
        assert gaps[np.triu_indices(len(rows), 1)].min() >= 25.0  # never two places of the same street
        seen += list(place_of[rows[:, 0]])
    # At most one pass over the places with K images or more; only a place that would be alone in its
    # batch (no negative: the tail of places too close to each other) waits for the next epoch.
    assert len(seen) == len(set(seen)) and all(counts[p] >= K for p in seen)
    assert len(seen) >= 0.9 * len(train.rows)
    # Group by group: a batch holds places of at most two consecutive groups.
    assert all(np.ptp([groups[p] for p in place_of[np.array(b)[::K]]]) <= 1 for b in batches)
    # The same epoch is drawn again after a resume; another epoch is another draw.
    assert epoch_batches(train, batching, 0) == batches and epoch_batches(train, batching, 1) != batches


def test_without_separation_batches_are_consecutive_places_as_gsv_cities_draws_them() -> None:
    places = _line_of_places([4] * 10, [0] * 5 + [1] * 5)
    train = training_places(places, K)
    batches = epoch_batches(train, PlaceBatching(3, K, separation=0.0, seed=0), epoch=0)
    order = [train.labels[b[i * K]] for b in batches for i in range(len(b) // K)]
    assert [len(b) // K for b in batches] == [3, 3, 3]  # the last place alone is dropped
    rng = np.random.default_rng([0, 0])
    expected = [int(p) for g in (0, 1) for p in rng.permutation(np.arange(5 * g, 5 * g + 5))]
    assert order == expected[:9]


def test_a_set_without_places_is_one_line() -> None:
    plain = PlaceSet("pitts", (Path("/a.jpg"),), (Path("/b.jpg"),), np.zeros((1, 2)), np.zeros((1, 2)))
    with pytest.raises(SemvprError, match="not grouped into places"):
        training_places(plain, K)


# ----------------------------------------------------------------------------------- miner and loss
def _reference_ms_loss(x: torch.Tensor, y: torch.Tensor, alpha: float, beta: float, base: float, eps: float):
    """Multi-similarity mining and loss written out from the paper's formulas (Wang et al., CVPR 2019)."""
    s = x @ x.T  # unit descriptors: cosine = dot product
    n = len(y)
    same = y[:, None] == y[None]
    off = ~torch.eye(n, dtype=torch.bool)
    pos, neg = same & off, ~same
    hardest_neg = torch.where(neg, s, torch.tensor(-torch.inf)).max(1).values
    easiest_pos = torch.where(pos, s, torch.tensor(torch.inf)).min(1).values
    keep_pos = pos & (s - eps < hardest_neg[:, None])
    keep_neg = neg & (s + eps > easiest_pos[:, None])
    total = x.new_zeros(())
    for i in range(n):
        p_term = torch.log1p(torch.exp(-alpha * (s[i][keep_pos[i]] - base)).sum()) / alpha
        n_term = torch.log1p(torch.exp(beta * (s[i][keep_neg[i]] - base)).sum()) / beta
        total = total + p_term + n_term
    return total / n, int(keep_pos.sum()), int(keep_neg.sum())


def test_the_recipe_loss_is_pytorch_metric_learning_ms_loss_with_its_miner() -> None:
    loss = settings_of(config("recipe=gsv"), training=True).training.optimization.loss
    assert isinstance(loss, MultiSimilarity)
    assert isinstance(loss.loss, losses.MultiSimilarityLoss) and isinstance(loss.miner, miners.MultiSimilarityMiner)
    # gsv-cities' settings: alpha 1, beta 50, base 0, epsilon 0.1; dot-product loss, cosine miner.
    assert (loss.loss.alpha, loss.loss.beta, loss.loss.base, loss.miner.epsilon) == (1.0, 50.0, 0.0, 0.1)
    assert isinstance(loss.loss.distance, distances.DotProductSimilarity)
    assert isinstance(loss.miner.distance, distances.CosineSimilarity)
    # A tiny batch, P = 3 places × K = 4: the same value and gradient as the library called directly, and as
    # the formulas written out (so the wiring passes the miner's pairs, not all pairs).
    gen = torch.Generator().manual_seed(0)
    centre = torch.randn(3, 16, generator=gen)
    raw = centre.repeat_interleave(K, 0) + 0.9 * torch.randn(12, 16, generator=gen)
    labels = torch.arange(3).repeat_interleave(K)
    ours_x = F.normalize(raw, dim=1).requires_grad_()
    direct_x = F.normalize(raw, dim=1).requires_grad_()
    ours = loss(ours_x, {"labels": labels})
    direct_loss = losses.MultiSimilarityLoss(alpha=1, beta=50, base=0, distance=distances.DotProductSimilarity())
    direct_miner = miners.MultiSimilarityMiner(epsilon=0.1, distance=distances.CosineSimilarity())
    direct = direct_loss(direct_x, labels, direct_miner(direct_x, labels))
    reference, kept_pos, kept_neg = _reference_ms_loss(F.normalize(raw, dim=1), labels, 1.0, 50.0, 0.0, 0.1)
    all_pairs = losses.MultiSimilarityLoss(alpha=1, beta=50, base=0)(F.normalize(raw, dim=1), labels)
    assert 0 < kept_pos < 12 * 3 and 0 < kept_neg < 12 * 8  # mining kept some pairs and dropped others
    assert ours.item() == pytest.approx(direct.item(), rel=1e-6) and ours.item() == pytest.approx(
        reference.item(), rel=1e-5
    )
    assert abs(all_pairs.item() - ours.item()) > 1e-3
    ours.backward(), direct.backward()
    assert torch.allclose(ours_x.grad, direct_x.grad, atol=1e-7) and ours_x.grad.abs().sum() > 0


def test_the_loss_runs_in_float32_under_bf16_autocast() -> None:
    """Training runs under bf16 autocast; similarities rounded to bf16 would move exp(50·s) by e^0.4."""
    gen = torch.Generator().manual_seed(1)
    x = F.normalize(torch.randn(16, 64, generator=gen), dim=1)
    labels = torch.arange(4).repeat_interleave(K)
    loss = MultiSimilarity()
    exact = loss(x, {"labels": labels})
    with torch.autocast("cpu", dtype=torch.bfloat16):
        under = loss(x, {"labels": labels})
    assert under.dtype == torch.float32 and under.item() == pytest.approx(exact.item(), rel=1e-6)


def test_each_aggregator_takes_its_published_schedule_else_gsv_cities_own() -> None:
    def schedule(aggregator: str) -> tuple:
        r = config("recipe=gsv", f"aggregator={aggregator}").recipe
        return r.optimizer._target_, r.optimizer.lr, r.scheduler._target_.rsplit(".", 1)[1], r.scheduler_interval

    assert schedule("mixvpr") == ("torch.optim.SGD", 0.05, "MultiStepLR", "epoch")
    assert schedule("salad") == ("torch.optim.AdamW", 6e-5, "LinearLR", "step")
    assert (
        schedule("boq")[:2] == ("torch.optim.AdamW", 1e-4)
        and config("recipe=gsv", "aggregator=boq").recipe.warmup_steps > 0
    )
    assert schedule("gem") == schedule("netvlad") == ("torch.optim.AdamW", 2e-4, "MultiStepLR", "epoch")
    gsv = config("recipe=gsv", "aggregator=mixvpr")
    assert gsv.trainer.max_epochs == gsv.aggregator.gsv.max_epochs and gsv.data.train.traversals == 4
    # recipe=triplet is untouched: its own optimizer, 16 epochs, no extra traversals.
    triplet = config()
    assert (triplet.recipe.name, triplet.recipe.optimizer.lr, triplet.trainer.max_epochs) == ("triplet", 1e-3, 16)
    assert triplet.data.train.traversals == 0 and "loss" not in triplet.recipe


def test_warm_up_scales_every_group_linearly_then_leaves_the_rate_to_the_scheduler(tmp_path: Path) -> None:
    cfg = tiny_config(tmp_path, "recipe=gsv", "aggregator=gem", "recipe.warmup_steps=4")
    backbone = build_backbone(cfg.backbone, 0)
    retriever = build_retriever(settings_of(cfg, training=True), backbone, None)
    optimizer = retriever.configure_optimizers()["optimizer"]
    rates = []
    for step in range(6):
        retriever._trainer = SimpleNamespace(global_step=step)
        retriever.optimizer_step(0, step, optimizer, None)
        rates.append(optimizer.param_groups[0]["lr"])
    assert rates == pytest.approx([5e-5, 1e-4, 1.5e-4, 2e-4, 2e-4, 2e-4])


# ----------------------------------------------------------------------------------- GSV-Cities layout
def test_gsv_cities_reader_builds_names_as_gsv_cities_and_groups_places_by_city(tmp_path: Path) -> None:
    root = write_gsv_cities(tmp_path / "gsv")
    places = read_gsv_cities(root, ["London", "OSL", "Boston"])
    sizes = [n for _, ps in GSV_CITIES.values() for _, n in ps]
    assert len(places.db_paths) == sum(sizes) and places.q_paths == ()
    # One name checked by hand against the rule (the fixture's csv holds lat 51.6161000).
    row = gsv_row("London", 130, 2)
    expected = root / "Images" / "London" / "London_0000130_2009_11_310_51.6161_-0.21951510000000002_p130-2_Xy2.jpg"
    assert gsv_name(row) == expected.name and expected in places.db_paths
    assert all(p.is_file() for p in places.db_paths)
    ids = places.place_ids
    assert ids.num_places == 10 and list(ids.groups) == [0] * 5 + [1] * 3 + [2] * 2
    # Every place's images share its city and place id (OSL's 130 is another place than London's 130).
    by_place = defaultdict(set)
    for path, pid in zip(places.db_paths, ids.db):
        city_id, number = path.name.split("_")[:2]
        by_place[int(pid)].add((city_id, int(number)))
    assert all(len(v) == 1 for v in by_place.values()) and len({next(iter(v)) for v in by_place.values()}) == 10
    assert sorted(Counter(ids.db.tolist()).values()) == sorted(sizes)
    # Cities never come within any radius of each other; a city's places lie within a few km.
    city_of = ids.groups[ids.db]
    east = places.db_utm[:, 0]
    assert (
        east[city_of == 1].min() - east[city_of == 0].max() > 1e6 and np.ptp(places.db_utm[city_of == 0], 0).max() < 2e4
    )
    # The place with 2 images (< K) is in the set, and left out of training.
    train = training_places(places, K)
    assert train.left_out == 1 and len(train.rows) == 9
    assert read_gsv_cities(root).name == "gsv-cities/Boston+London+OSL"  # every csv, sorted


@pytest.mark.parametrize(
    "damage,fragment",
    [
        ("bad year", "London.csv: line 3: year='20x8' is not a whole number"),
        ("missing image", "London.csv: 1 of its 21 images are missing, the first"),
        ("missing column", "London.csv: missing column(s) ['panoid']"),
        ("unknown city", "no dataframe for city 'Paris'"),
        ("field over the csv limit", "London.csv: line 3: not a readable csv row (field larger than field limit"),
        ("latin-1 bytes", "London.csv: not UTF-8 text (a byte 0xe9)"),
        ("a FIFO", "London.csv is not a regular file"),
    ],
)
def test_gsv_cities_damage_is_one_line(tmp_path: Path, damage: str, fragment: str) -> None:
    root = write_gsv_cities(tmp_path / "gsv")
    csv = root / "Dataframes" / "London.csv"
    lines = csv.read_text().splitlines()
    cities = ["London", "OSL"]
    if damage == "bad year":
        fields = lines[2].split(",")
        fields[1] = "20x8"
        lines[2] = ",".join(fields)
        csv.write_text("\n".join(lines) + "\n")
    elif damage == "missing image":
        next((root / "Images" / "London").iterdir()).unlink()
    elif damage == "missing column":
        csv.write_text("\n".join(line.rsplit(",", 1)[0] for line in lines) + "\n")
    elif damage == "field over the csv limit":
        csv.write_text("\n".join([*lines[:2], lines[2] + "x" * 200_000, *lines[3:]]) + "\n")
    elif damage == "latin-1 bytes":
        csv.write_bytes(("\n".join(lines[:2]) + "\n").encode() + "caf\u00e9,1\n".encode("latin-1"))
    elif damage == "a FIFO":
        csv.unlink()
        os.mkfifo(csv)
    else:
        cities = ["London", "Paris"]
    with pytest.raises(SemvprError) as err:
        read_gsv_cities(root, cities)
    assert fragment in str(err.value) and "\n" not in str(err.value)


# ----------------------------------------------------------------------------------- SynthCity places
def test_synthcity_training_places_have_k_images_from_different_traversals(gsv_cache: Path) -> None:
    root = ensure_synthcity(gsv_cache, "tiny", 0, None, [64, 80])
    before = {p: p.stat().st_mtime_ns for p in root.rglob("*")}
    drawn = read_split("tiny", 0, gsv_cache, "train", image_size=[64, 80])
    places = read_split("tiny", 0, gsv_cache, "train", image_size=[64, 80], traversals=4)
    # The dataset itself is untouched: its files, and the split as drawn (what recipe=triplet mines).
    assert {p: p.stat().st_mtime_ns for p in root.rglob("*")} == before
    plain = read_utm_folder(root, "train")
    assert drawn.db_paths == plain.db_paths and drawn.q_paths == plain.q_paths
    assert np.array_equal(drawn.q_utm, plain.q_utm) and places.db_paths == drawn.db_paths
    assert places.q_paths[: len(drawn.q_paths)] == drawn.q_paths
    assert places.semantic_source.q_paths == drawn.q_paths and places.semantic_source.root == drawn.root
    # Every place (one per 5 m database position) holds 1 + 4 images from 5 different traversals
    # (the @UTM@ timestamp field), all within a half step of its position.
    ids = np.concatenate([places.place_ids.db, places.place_ids.q])
    paths = places.db_paths + places.q_paths
    utm = np.concatenate([places.db_utm, places.q_utm])
    dates = defaultdict(set)
    for path, pid in zip(paths, ids):
        dates[int(pid)].add(path.name.split("@")[13])
    assert len(dates) == 24 and min(len(d) for d in dates.values()) >= 5
    for pid in dates:
        assert np.ptp(utm[ids == pid, 0]) <= 5.0
    assert all(label.is_file() for label in places.q_labels)
    assert read_split("tiny", 0, gsv_cache, "val", image_size=[64, 80]).q_paths == read_utm_folder(root, "val").q_paths


def test_the_default_synthcity_keeps_its_cache_key() -> None:
    from semvpr.core.cache import artifact_dir
    from semvpr.data.synthcity import _key

    # The keys of the datasets recipe=triplet has always used (their files are drawn by the same code).
    assert artifact_dir("c", "synthcity", _key("default", 0, {}, [180, 240])).name == "synthcity-f9efea24eeac"
    assert artifact_dir("c", "synthcity", _key("tiny", 0, {}, [64, 80])).name == "synthcity-99b2d0808b21"


# ----------------------------------------------------------------------------------- whole jobs
@pytest.mark.parametrize(
    "overrides",
    [
        ("aggregator=mixvpr", "mask=oracle"),
        ("aggregator=netvlad", "backbone.train_from=stage4"),
    ],
)
def test_fast_dev_run_of_the_gsv_recipe(gsv_cache: Path, tmp_path: Path, overrides: tuple[str, ...]) -> None:
    cfg = tiny_config(gsv_cache, "recipe=gsv", *overrides, "+trainer.fast_dev_run=true")
    metrics = run_job(cfg, tmp_path)
    assert metrics["recipe"] == "gsv" and metrics["status"] == "ok" and 0.0 <= metrics["test/R@1"] <= 100.0
    assert metrics["places"] == 24 and metrics["places_per_epoch"] >= 20
    assert metrics["recipe_settings"]["images_per_place"] == 4


def test_gsv_cities_trains_and_is_scored_on_synthcity(gsv_cache: Path, tmp_path: Path) -> None:
    root = write_gsv_cities(tmp_path / "gsv")
    cfg = tiny_config(
        gsv_cache, "recipe=gsv", "data=gsv_cities", f"data.root={root}", "aggregator=gem", "+trainer.fast_dev_run=true"
    )
    metrics = run_job(cfg, tmp_path / "run")
    assert (metrics["data"], metrics["places"], metrics["recipe"]) == ("gsv_cities", 9, "gsv")
    triplet = tiny_config(gsv_cache, "data=gsv_cities", f"data.root={root}", "+trainer.fast_dev_run=true")
    with pytest.raises(SemvprError, match="has none \\(it is a set of places\\): train it with recipe=gsv"):
        run_job(triplet, tmp_path / "triplet")


@pytest.mark.reproducibility
def test_resumed_gsv_run_ends_as_the_uninterrupted_one(gsv_cache: Path, tmp_path: Path) -> None:
    # MixVPR's warm-up (25 steps) spans both epochs, so the resumed run must also continue its rates.
    args = ("recipe=gsv", "aggregator=mixvpr")
    whole = run_job(tiny_config(gsv_cache, *args, "trainer.max_epochs=2"), tmp_path / "whole")
    run_dir = tmp_path / "run"
    run_job(tiny_config(gsv_cache, *args, "trainer.max_epochs=1"), run_dir)
    resumed = run_job(tiny_config(gsv_cache, *args, "trainer.max_epochs=2", "ckpt_path=last"), run_dir)
    last = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True)
    assert last["epoch"] == 1 and resumed["recalls"] == whole["recalls"]
    weights = [torch.load(m["checkpoint"], weights_only=True)["state_dict"] for m in (resumed, whole)]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


@pytest.mark.slow
def test_every_aggregator_trains_with_the_gsv_recipe_in_one_sweep(tmp_path: Path) -> None:
    """The issue's command: ``-m experiment=tiny recipe=gsv aggregator=... mask=none,oracle``, every job ok,
    one report row per aggregator and mask, marked with the recipe."""
    sweep = tmp_path / "sweep"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.train",
            "-m",
            "experiment=tiny",
            "recipe=gsv",
            "aggregator=netvlad,gem,mixvpr,salad,boq",
            "mask=none,oracle",
            f"paths.cache_dir={tmp_path / 'cache'}",
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = [json.loads(p.read_text()) for p in sweep.rglob("metrics.json")]
    assert len(jobs) == 10 and all(j["status"] == "ok" and j["recipe"] == "gsv" for j in jobs)
    report = (sweep / "results.md").read_text()
    for aggregator in ("netvlad", "gem", "mixvpr", "salad", "boq"):
        assert f"{aggregator} (gsv) · none" in report and f"{aggregator} (gsv) · oracle" in report

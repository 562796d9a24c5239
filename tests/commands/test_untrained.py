"""Off-the-shelf baselines: ``semvpr.eval ckpt=none`` evaluates the config's model with no VPR training
(pretrained trunk, the aggregator's untrained form), and frame-aligned sets (``data=frames``) through the
real CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from semvpr.core.errors import SemvprError
from tests.helpers import FRAME_SIZE, REPO, config, frame_images, make_folder, write_frames, write_student_dir

SIZE = [f"data.image_size=[{FRAME_SIZE[0]},{FRAME_SIZE[1]}]", "data.num_workers=0"]
#: The tiny SynthCity a NetVLAD / SRAL k-means reads in these tests (the training tests' size).
TINY_INIT = ["experiment=tiny", "init.overrides=['preset=tiny','image_size=[64,80]']"]


def cli(tmp: Path, *args: str) -> subprocess.CompletedProcess:
    """``python -m semvpr.eval args`` from an empty directory, run and cache dirs under ``tmp``."""
    (tmp / "cwd").mkdir(parents=True, exist_ok=True)
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.eval",
            *args,
            f"paths.cache_dir={tmp / 'cache'}",
            f"hydra.run.dir={tmp / 'run'}",
        ],
        cwd=tmp / "cwd",
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=600,
    )


def last_json(proc: subprocess.CompletedProcess) -> dict:
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two traversals of 6 frames; night frame i shows day frame i + 1's image (day frame 0's nowhere)."""
    return write_frames(tmp_path_factory.mktemp("frames"), {"day": [0, 1, 2, 3, 4, 5], "night": [1, 2, 3, 4, 5, 9]})


def frames_args(root: Path, window: int) -> list[str]:
    return [
        "data=frames",
        f"data.root={root}",
        "data.database=day",
        "data.queries=night",
        f"data.frame_window={window}",
    ]


def test_cli_untrained_gem_is_gem_p3_of_the_trunk_features(frames: Path, tmp_path: Path) -> None:
    """ckpt=none aggregator=gem: the pretrained trunk's features pooled by GeM at p = 3 without a head,
    re-derived here from the trunk's output (bf16, as the pipeline holds it) in float64."""
    from semvpr.core.precision import autocast
    from semvpr.models.backbones import EfficientNetLite0Backbone

    result = last_json(cli(tmp_path, "ckpt=none", "aggregator=gem", *frames_args(frames, 1), *SIZE))
    assert (result["checkpoint"], result["aggregator"], result["mask"], result["descriptor_dim"]) == (
        "none",
        "gem",
        "none",
        112,
    )
    backbone = EfficientNetLite0Backbone(weights="imagenet").eval()
    expected = {}
    for side in ("day", "night"):
        with torch.no_grad(), autocast("cpu"):
            trunk = backbone.forward_frozen(frame_images(frames, side), keep_scales=False)[-1]
        x = trunk.to(torch.bfloat16).double().numpy()
        pooled = (np.clip(x, 1e-6, None) ** 3).mean(axis=(2, 3)) ** (1 / 3)
        expected[side] = pooled / np.linalg.norm(pooled, axis=1, keepdims=True)
    cached = [np.load(d / "descriptors.npy") for d in (tmp_path / "cache").glob("descriptors-*")]
    assert len(cached) == 2  # database and queries
    for side, want in expected.items():
        assert any(np.allclose(c, want, rtol=0, atol=1e-5) for c in cached), side
    assert not np.allclose(expected["day"], expected["night"])


def test_cli_frames_positives_are_the_frame_window(frames: Path, tmp_path: Path) -> None:
    """Night frame i is day frame i + 1's image: its nearest neighbour is a positive within ±1, not ±0."""
    one = last_json(cli(tmp_path, "ckpt=none", "aggregator=gem", *frames_args(frames, 1), *SIZE))
    assert one["set"] == f"{frames.name} day→night ±1" and one["data"] == "frames"
    assert (one["database"], one["queries"], one["benchmark"]) == (6, 6, None)
    # The last night frame shows an image no day frame has: 5 of 6 retrieve their own image.
    assert one["test/R@1"] >= round(100 * 5 / 6, 2)
    from semvpr.eval import evaluate_checkpoint

    cache = f"paths.cache_dir={tmp_path / 'cache'}"
    cfg = config("+ckpt=none", "aggregator=gem", *frames_args(frames, 0), *SIZE, cache, config_name="eval")
    zero = evaluate_checkpoint(cfg, {"aggregator"})
    assert zero["set"] == f"{frames.name} day→night ±0"
    assert zero["test/R@1"] <= round(100 / 6, 2)  # the identical image is one frame off: not a positive


def test_the_gardens_point_preset_names_its_traversals(tmp_path: Path) -> None:
    from semvpr.config.build import build_places
    from semvpr.config.plan import data_settings

    root = write_frames(
        tmp_path / "gp", {t: list(range(5)) for t in ("day_left", "day_right", "night_right")}, name="Image{:03d}.jpg"
    )
    (root / "night_right" / "Thumbs.db").write_bytes(b"")  # not an image: not read
    cfg = config("data=gardens_point", f"data.root={root}", "+ckpt=none", config_name="eval")
    assert list(cfg.data.image_size) == [270, 480] and cfg.data.frame_window == 2
    test = build_places(data_settings(cfg), ("test",))["test"]
    assert test.name == "gardens_point day_left→night_right ±2"
    assert [p.tolist() for p in test.positives()] == [[0, 1, 2], [0, 1, 2, 3], [0, 1, 2, 3, 4], [1, 2, 3, 4], [2, 3, 4]]
    other = config(
        "data=gardens_point", f"data.root={root}", "data.database=day_right", "+ckpt=none", config_name="eval"
    )
    assert build_places(data_settings(other), ("test",))["test"].name == "gardens_point day_right→night_right ±2"


def test_nordland_keeps_its_commands_and_protocol_id(tmp_path: Path) -> None:
    from semvpr.config.build import build_places
    from semvpr.config.plan import data_settings

    root = write_frames(tmp_path / "nordland", {"ref": [0, 1, 2], "query": [0, 1, 2]}, name="{:05d}.png")
    cfg = config("data=nordland", f"data.root={root}", "data.frame_window=1", "+ckpt=none", config_name="eval")
    assert cfg.data.benchmark == "nordland±1"  # published-number lookups key on the protocol id
    assert build_places(data_settings(cfg), ("test",))["test"].name == "nordland ref→query ±1"


REFUSED = {
    "mixvpr": (["aggregator=mixvpr"], "ckpt=none: aggregator=mixvpr has no untrained form"),
    "salad": (["aggregator=salad"], "ckpt=none: aggregator=salad has no untrained form"),
    "boq": (["aggregator=boq"], "ckpt=none: aggregator=boq has no untrained form"),
    "gem-with-head": (
        ["aggregator=gem", "aggregator.fc_dim=512"],
        "ckpt=none: aggregator.fc_dim=512 has no untrained form",
    ),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_aggregators_without_an_untrained_form_are_refused(frames: Path, tmp_path: Path, case: str) -> None:
    overrides, fragment = REFUSED[case]
    with pytest.raises(SemvprError, match=fragment) as err:
        untrained(tmp_path, *overrides, root=frames)
    assert "\n" not in str(err.value) and not (tmp_path / "cache").exists()


@pytest.mark.parametrize(
    "case", ["mixvpr", "gem-with-head", *(pytest.param(c, marks=pytest.mark.slow) for c in ("salad", "boq"))]
)
def test_cli_refuses_aggregators_without_an_untrained_form(frames: Path, tmp_path: Path, case: str) -> None:
    overrides, fragment = REFUSED[case]
    proc = cli(tmp_path, "ckpt=none", *overrides, *frames_args(frames, 1), *SIZE)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"semvpr: error: {fragment}"), proc.stderr
    assert "one of aggregator=gem, netvlad, sral" in lines[0] or "drop the override" in lines[0]
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


def untrained(tmp: Path, *overrides: str, explicit: set[str] = frozenset(), root: Path | None = None):
    from semvpr.config.restore import load_retriever

    data = frames_args(root, 1) if root is not None else []
    cfg = config("+ckpt=none", f"paths.cache_dir={tmp}", *TINY_INIT, *data, *SIZE, *overrides, config_name="eval")
    evaluated = () if root is None else tuple(sorted((root / "day").iterdir()))
    return load_retriever(cfg, {o.split("=", 1)[0] for o in overrides} | set(explicit), evaluated=lambda: evaluated)


@pytest.mark.parametrize("aggregator", ["netvlad", "sral"])
def test_untrained_netvlad_and_sral_are_a_training_runs_initialisation(tmp_path: Path, aggregator: str) -> None:
    """Their untrained form is exactly what a training run on init.data starts from (the same k-means on the
    same sample of its training database images), not the construction's random centroids."""
    from semvpr.config.build import build_retriever, init_aggregator, prepare
    from semvpr.config.plan import job_plan
    from tests.helpers import tiny_config

    retriever, _ = untrained(tmp_path, f"aggregator={aggregator}")
    train_cfg = tiny_config(tmp_path, f"aggregator={aggregator}")
    plan = job_plan(train_cfg)
    job = prepare(plan, {})
    reference = build_retriever(plan.settings, job.backbone, None)
    constructed = {k: v.clone() for k, v in reference.aggregator.state_dict().items()}
    init_aggregator(plan.settings, reference, job)
    for name, value in reference.aggregator.state_dict().items():
        assert torch.equal(retriever.aggregator.state_dict()[name], value), name
    assert not torch.equal(constructed["centroids"], reference.aggregator.state_dict()["centroids"])


def test_an_untrained_model_is_on_the_jobs_device_before_its_initialisation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """ckpt=none's trunk pass, k-means (and SRAL's teacher) run where the job runs: the retriever is moved to
    the device load_retriever is given before it is initialised, not after (they ran on the CPU before a GPU
    job's model moved)."""
    from semvpr.config import restore
    from semvpr.retrieval.retriever import Retriever

    events: list[tuple[str, object]] = []
    to, initialise = Retriever.to, restore.initialise_untrained

    def spy_to(self: Retriever, *args: object, **kwargs: object) -> Retriever:
        events.append(("to", args[0] if args else kwargs.get("device")))
        return to(self, *args, **kwargs)

    def spy_initialise(cfg: object, retriever: Retriever, evaluated: object) -> str:
        events.append(("initialise", next(retriever.backbone.parameters()).device))
        return initialise(cfg, retriever, evaluated)

    monkeypatch.setattr(Retriever, "to", spy_to)
    monkeypatch.setattr(restore, "initialise_untrained", spy_initialise)
    device = torch.device("cpu", 0)  # the CPU under a name no other call moves a module to
    cfg = config(
        "+ckpt=none", f"paths.cache_dir={tmp_path}", *TINY_INIT, *SIZE, "aggregator=netvlad", config_name="eval"
    )
    restore.load_retriever(cfg, {"aggregator"}, device=device)
    kinds = [kind for kind, _ in events]
    assert "initialise" in kinds and ("to", device) in events[: kinds.index("initialise")], events


def test_the_kmeans_never_reads_the_evaluated_set(tmp_path: Path) -> None:
    """init.data naming the evaluated images (here a folder whose train split is its test split) is refused."""
    root = make_folder(tmp_path / "folder", n=3)
    (root / "images" / "train").symlink_to(root / "images" / "test", target_is_directory=True)
    from semvpr.config.restore import load_retriever

    cfg = config(
        "+ckpt=none",
        "aggregator=netvlad",
        "data=folder",
        f"data.root={root}",
        "init.data=folder",
        f"init.root={root}",
        f"paths.cache_dir={tmp_path / 'cache'}",
        *SIZE,
        config_name="eval",
    )
    evaluated = tuple((root / "images" / "test" / "database").iterdir())
    with pytest.raises(SemvprError, match=r"init.data=folder: 3 of its training images are evaluated here"):
        load_retriever(cfg, {"aggregator"}, evaluated=lambda: evaluated)
    cfg.init.data = "frames"
    with pytest.raises(SemvprError, match=r"init.data=frames has no train split"):
        load_retriever(cfg, {"aggregator"}, evaluated=lambda: evaluated)


def test_untrained_models_with_a_student_directory_and_the_refusals(frames: Path, tmp_path: Path) -> None:
    from semvpr.config.build import build_backbone, build_places
    from semvpr.config.plan import data_settings
    from semvpr.retrieval.descriptors import place_descriptors
    from tests.helpers import tiny_config

    backbone = build_backbone(tiny_config(tmp_path).backbone, 0).eval()
    student = write_student_dir(tmp_path / "student", backbone, frame_images(frames, "day"))
    plain, merged = untrained(tmp_path, "aggregator=gem", root=frames)
    masked, _ = untrained(tmp_path, "aggregator=gem", "mask=student", f"student.checkpoint={student}", root=frames)
    assert masked.aggregator.fc is None and masked.mask_source.student.trained_on.name == "camvid"
    test = build_places(data_settings(merged), ("test",))["test"]
    a = place_descriptors(plain, test, "db", merged.data.image_size, tmp_path / "d")
    b = place_descriptors(masked, test, "db", merged.data.image_size, tmp_path / "d")
    assert not np.allclose(a, b)
    for overrides, fragment in (
        (["aggregator=gem", "mask=teacher"], "ckpt=none: mask=teacher needs a saved teacher"),
        (["aggregator=gem", "model.pca_dim=16"], "ckpt=none: model.pca_dim=16 is a whitening"),
        (["filter=unet", "filter.weights=learned", f"student.checkpoint={student}"], "ckpt=none: mask.weights=learned"),
    ):
        with pytest.raises(SemvprError, match=fragment):
            untrained(tmp_path, *overrides, root=frames)


def test_the_hub_gives_untrained_models(tmp_path: Path) -> None:
    from semvpr.hub import load_model

    model = load_model("none", overrides=["aggregator=gem", f"paths.cache_dir={tmp_path}"])
    assert model.feature_dim == 112
    out = model(torch.rand(2, 3, *FRAME_SIZE))
    torch.testing.assert_close(out.norm(dim=1), torch.ones(2))


def test_training_refuses_a_student_directory(tmp_path: Path) -> None:
    from semvpr.config.checks import check_config
    from tests.helpers import tiny_config

    with pytest.raises(SemvprError, match=r"student.checkpoint=/x: a saved student is read by semvpr.eval"):
        check_config(tiny_config(tmp_path, "filter=unet", "student.checkpoint=/x"))

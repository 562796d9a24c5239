"""Another mask source at evaluation: ``mask=student student.checkpoint=DIR`` / ``mask=teacher
teacher.checkpoint=DIR`` / ``mask=none`` replace a checkpoint's own, through the real CLIs; the aggregator
(and learned class weights) stay the checkpoint's; student directories are read as data; a checkpoint
whose mask was trained on SynthCity warns once on real images."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from semvpr.core.errors import SemvprError
from tests.helpers import (
    FRAME_SIZE,
    REPO,
    config,
    frame_images,
    tiny_config,
    write_checkpoint,
    write_frames,
    write_student_dir,
    write_teacher_dir,
)

SIZE = [f"data.image_size=[{FRAME_SIZE[0]},{FRAME_SIZE[1]}]", "data.num_workers=0"]


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A frame-aligned set, checkpoints (no mask; SynthCity student mask, binary and learned) and a
    student and a teacher directory."""
    from semvpr.config.build import build_backbone

    tmp = tmp_path_factory.mktemp("override")
    frames = write_frames(tmp / "frames", {"day": [0, 1, 2, 3, 4, 5], "night": [0, 1, 2, 3, 4, 5]})
    paths = {"frames": frames}
    for name, overrides in {
        "plain": ["filter=attention"],
        "unet": ["filter=unet"],
        "learned": ["filter=unet", "filter.weights=learned"],
    }.items():
        cfg = tiny_config(tmp / "cache", *overrides)
        write_checkpoint(cfg, tmp / f"{name}.ckpt")
        paths[name] = tmp / f"{name}.ckpt"
    # Learned class weights away from their start, so keeping them is visible.
    data = torch.load(paths["learned"], weights_only=True)
    data["state_dict"]["class_weights.theta"] = torch.linspace(-3.0, 3.0, 19)
    torch.save(data, paths["learned"])
    backbone = build_backbone(tiny_config(tmp / "cache").backbone, 0).eval()
    paths["student"] = write_student_dir(
        tmp / "seg" / "student_efficientnet_lite0", backbone, frame_images(frames, "day")
    )
    paths["teacher"] = write_teacher_dir(tmp / "seg" / "teacher")
    return paths


def frames_args(world: dict[str, Path]) -> list[str]:
    return ["data=frames", f"data.root={world['frames']}", "data.database=day", "data.queries=night", *SIZE]


def cli(tmp: Path, *args: str, module: str = "semvpr.eval") -> subprocess.CompletedProcess:
    """``python -m <module> args`` from an empty directory, run and cache dirs under ``tmp``."""
    (tmp / "cwd").mkdir(parents=True, exist_ok=True)
    return subprocess.run(
        [
            sys.executable,
            "-m",
            module,
            *args,
            f"paths.cache_dir={tmp / 'cache'}",
            f"hydra.run.dir={tmp / 'run'}",
            "threads=1",
        ],
        cwd=tmp / "cwd",
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=600,
    )


def descriptor_caches(cache: Path) -> dict[str, np.ndarray]:
    """Every cached descriptor array, by its cache directory's name."""
    return {d.name: np.load(d / "descriptors.npy") for d in sorted(cache.glob("descriptors-*"))}


def load(world: dict[str, Path], ckpt: str, tmp: Path, *overrides: str):
    from semvpr.config.restore import load_retriever

    cfg = config(*frames_args(world), f"+ckpt={world[ckpt]}", f"paths.cache_dir={tmp}", *overrides, config_name="eval")
    explicit = {o.split("=", 1)[0].lstrip("+") for o in overrides}
    return load_retriever(cfg, explicit)


def checkpoint_state(path: Path, prefix: str) -> dict[str, torch.Tensor]:
    state = torch.load(path, weights_only=True)["state_dict"]
    return {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}


def descriptors(world: dict[str, Path], ckpt: str, cache: Path, *overrides: str) -> tuple[np.ndarray, object]:
    """The database descriptors of the frames set, computed in this process into ``cache``, and the retriever,
    at the CLI's thread count (``threads=1``, :func:`cli`): on a CPU whose frozen passes are not
    thread-invariant (seen on an AMD EPYC with AVX512-BF16: 2e-8 apart at 1 and 2 threads), descriptors made
    at another count differ in their last bits, which is not what these tests compare."""
    from semvpr.config.build import build_places
    from semvpr.config.plan import data_settings
    from semvpr.retrieval.descriptors import place_descriptors

    retriever, merged = load(world, ckpt, cache, *overrides)
    test = build_places(data_settings(merged), ("test",))["test"]
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return np.array(place_descriptors(retriever, test, "db", merged.data.image_size, cache)), retriever
    finally:
        torch.set_num_threads(before)


@pytest.mark.reproducibility
def test_cli_student_directory_replaces_the_mask_and_keeps_the_aggregator(
    world: dict[str, Path], tmp_path: Path
) -> None:
    """A checkpoint trained without a mask, evaluated with a student directory's: other descriptors, the
    checkpoint's aggregator weights, the directory's student weights; the CLI's descriptors are the model's."""
    overrides = ["mask=student", f"student.checkpoint={world['student']}"]
    masked = cli(tmp_path, f"ckpt={world['plain']}", *frames_args(world), *overrides)
    assert masked.returncode == 0, masked.stderr
    result = json.loads(masked.stdout.strip().splitlines()[-1])
    assert (result["mask"], result["mask_checkpoint"], result["aggregator"]) == (
        "student",
        str(world["student"]),
        "sral",
    )
    assert "warning" not in masked.stderr
    cached = descriptor_caches(tmp_path / "cache")
    assert len(cached) == 2  # database and queries

    unmasked, _ = descriptors(world, "plain", tmp_path / "a")
    ours, retriever = descriptors(world, "plain", tmp_path / "b", *overrides)
    assert any(np.array_equal(ours, c) for c in cached.values())
    assert not np.allclose(ours, unmasked)
    for name, value in checkpoint_state(world["plain"], "aggregator.").items():
        assert torch.equal(retriever.aggregator.state_dict()[name], value), name
    stored = load_file(world["student"] / "model.safetensors")
    assert all(torch.equal(retriever.mask_source.student.state_dict()[k], v) for k, v in stored.items())
    assert retriever.mask_source.student.trained_on.name == "camvid"


@pytest.mark.reproducibility
def test_cli_teacher_directory_replaces_the_mask_and_keeps_learned_class_weights(
    world: dict[str, Path], tmp_path: Path
) -> None:
    overrides = ["mask=teacher", f"teacher.checkpoint={world['teacher']}"]
    teacher = cli(tmp_path, f"ckpt={world['learned']}", *frames_args(world), *overrides)
    assert teacher.returncode == 0, teacher.stderr
    assert json.loads(teacher.stdout.strip().splitlines()[-1])["mask"] == "teacher"
    cached = descriptor_caches(tmp_path / "cache")

    own, _ = descriptors(world, "learned", tmp_path / "a")
    ours, retriever = descriptors(world, "learned", tmp_path / "b", *overrides)
    assert any(np.array_equal(ours, c) for c in cached.values()) and not np.allclose(ours, own)
    assert torch.equal(retriever.class_weights.theta, torch.linspace(-3.0, 3.0, 19))
    for name, value in checkpoint_state(world["learned"], "aggregator.").items():
        assert torch.equal(retriever.aggregator.state_dict()[name], value), name
    stored = load_file(world["teacher"] / "model.safetensors")
    weights = retriever.mask_source.teacher.model.state_dict()
    assert stored and all(torch.equal(weights[k], v) for k, v in stored.items() if k in weights)
    # A semvpr.segment teacher sees images at the size it was trained at (its semvpr.json) ...
    assert retriever.mask_source.teacher.inference_size == (32, 48)
    # ... and the same teacher at another input size is another mask: another cache entry.
    descriptors(world, "learned", tmp_path / "b", *overrides, "teacher.inference_size=[16,24]")
    assert len(descriptor_caches(tmp_path / "b")) == 2


def test_mask_none_drops_the_mask_and_the_class_weights(world: dict[str, Path], tmp_path: Path) -> None:
    retriever, merged = load(world, "learned", tmp_path, "mask=none")
    assert retriever.mask_source is None and retriever.class_weights is None and merged.mask.name == "none"
    for name, value in checkpoint_state(world["learned"], "aggregator.").items():
        assert torch.equal(retriever.aggregator.state_dict()[name], value), name


def test_the_oracle_replaces_the_mask_and_keeps_learned_class_weights(world: dict[str, Path], tmp_path: Path) -> None:
    """mask=oracle in place of a checkpoint's student (on a set with label maps: SynthCity's, data.occluders'):
    no segmenter weights, the checkpoint's aggregator and class weights; on a set without label maps the first
    pass says what it needs in one line."""
    from semvpr.models.masks import OracleMask

    retriever, merged = load(world, "learned", tmp_path / "cache", "mask=oracle")
    assert isinstance(retriever.mask_source, OracleMask) and merged.mask.weights == "learned"
    assert not any(merged[group].checkpoint for group in ("student", "teacher"))
    torch.testing.assert_close(retriever.class_weights.theta.detach(), torch.linspace(-3.0, 3.0, 19))
    for name, value in checkpoint_state(world["learned"], "aggregator.").items():
        assert torch.equal(retriever.aggregator.state_dict()[name], value), name
    proc = cli(tmp_path, f"ckpt={world['unet']}", *frames_args(world), "mask=oracle")
    assert proc.returncode != 0 and "mask=oracle needs ground-truth label maps" in proc.stderr.strip().splitlines()[-1]


@pytest.mark.parametrize(
    ("ckpt", "overrides", "fragment"),
    [
        ("unet", ["mask=teacher"], "add teacher.checkpoint=DIR"),
        ("plain", ["student.checkpoint=DIR"], "student.checkpoint=DIR is not read unless .* add mask=student"),
        ("plain", ["mask=student", "student.checkpoint=DIR", "mask.weights=learned"], "no learned class weights"),
        ("learned", ["mask=student", "student.checkpoint=DIR", "mask.weights=binary"], "differs from .*learned"),
        ("unet", ["filter=mask2former"], "drop the filter= override"),
    ],
)
def test_replacements_that_cannot_hold_are_refused(
    world: dict[str, Path], tmp_path: Path, ckpt: str, overrides: list[str], fragment: str
) -> None:
    given = [o.replace("DIR", str(world["student"])) for o in overrides]
    with pytest.raises(SemvprError, match=fragment.replace("DIR", ".*")):
        load(world, ckpt, tmp_path, *given)


def test_cli_synthcity_mask_on_real_images_warns_once(
    world: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    own = cli(tmp_path, f"ckpt={world['unet']}", *frames_args(world))
    assert own.returncode == 0, own.stderr
    warnings = [line for line in own.stderr.splitlines() if "warning" in line]
    assert len(warnings) == 1, own.stderr
    assert "mask=student from a segmenter trained on synthcity (synthetic images)" in warnings[0]
    assert "applied to real images (data=frames)" in warnings[0]
    assert "mask=student student.checkpoint=DIR (<semvpr.segment run>/student_<backbone>)" in warnings[0]
    capsys.readouterr()
    load(world, "unet", tmp_path, "mask=student", f"student.checkpoint={world['student']}")
    assert "warning" not in capsys.readouterr().err  # the replacement is what the warning asks for


def test_no_warning_on_the_kind_of_images_the_mask_was_trained_on(
    world: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from semvpr.config.restore import load_retriever

    cfg = tiny_config(tmp_path, f"+ckpt={world['unet']}", config_name="eval")  # SynthCity
    load_retriever(cfg)
    assert "warning" not in capsys.readouterr().err


def test_the_segmenter_record_is_optional_and_checked(
    world: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Checkpoints written before the record load as before (no warning); a malformed record is refused."""
    data = torch.load(world["unet"], weights_only=True)
    assert data["hyper_parameters"]["segmenter"] == {"name": "synthcity", "domain": "synthetic"}
    del data["hyper_parameters"]["segmenter"]
    torch.save(data, tmp_path / "old.ckpt")
    paths = {**world, "old": tmp_path / "old.ckpt", "bad": tmp_path / "bad.ckpt"}
    capsys.readouterr()
    retriever, _ = load(paths, "old", tmp_path)
    assert retriever.mask_source is not None and "warning" not in capsys.readouterr().err
    data["hyper_parameters"]["segmenter"] = {"name": "synthcity", "domain": "alien"}
    torch.save(data, tmp_path / "bad.ckpt")
    with pytest.raises(SemvprError, match=r"segmenter.domain='alien' is not one of"):
        load(paths, "bad", tmp_path)


def test_a_recorded_student_directory_is_never_read(world: dict[str, Path], tmp_path: Path) -> None:
    """A checkpoint naming a local student directory (training never writes one) is refused unless the
    command names that directory itself, as for a recorded teacher directory."""
    data = torch.load(world["unet"], weights_only=True)
    data["hyper_parameters"]["config"]["student"]["checkpoint"] = str(world["student"])
    torch.save(data, tmp_path / "named.ckpt")
    paths = {**world, "named": tmp_path / "named.ckpt"}
    with pytest.raises(SemvprError, match=r"student.checkpoint='.*student_efficientnet_lite0' names a local path"):
        load(paths, "named", tmp_path)


# ---------------------------------------------------------------- student directories are data


def _copy_student(world: dict[str, Path], tmp: Path) -> Path:
    out = tmp / "student"
    out.mkdir()
    for name in ("model.safetensors", "student.json"):
        (out / name).write_bytes((world["student"] / name).read_bytes())
    return out


def _code(folder: Path) -> str:
    (folder / "modeling_student.py").write_text("import os\nos.system('touch /tmp/owned')\n")
    return "modeling_student.py (code)"


def _pickle(folder: Path) -> str:
    torch.save(load_file(folder / "model.safetensors"), folder / "student.pt")
    (folder / "model.safetensors").unlink()
    return "student.pt (a pickle)"


def _shape(folder: Path) -> str:
    state = load_file(folder / "model.safetensors")
    state["head.weight"] = torch.zeros(19, 9, 1, 1)
    save_file(state, folder / "model.safetensors")
    return "'head.weight' is [19, 9, 1, 1], the architecture in student.json makes [19, 8, 1, 1]"


def _target(folder: Path) -> str:
    record = json.loads((folder / "student.json").read_text())
    record["_target_"] = "os.system"
    (folder / "student.json").write_text(json.dumps(record))
    return "key '_target_' is not part of a student record"


def _trunk(folder: Path) -> str:
    record = json.loads((folder / "student.json").read_text())
    record["backbone"]["frozen"]["frozen"] = "0123456789abcdef"
    (folder / "student.json").write_text(json.dumps(record))
    return "decodes the frozen trunk of efficientnet_lite0 (EfficientNetLite0Backbone, train_from=None, weights 0123"


def _nan(folder: Path) -> str:
    state = load_file(folder / "model.safetensors")
    state["head.bias"] = torch.full_like(state["head.bias"], float("nan"))
    save_file(state, folder / "model.safetensors")
    return "'head.bias' is not finite"


def _missing(folder: Path) -> str:
    state = load_file(folder / "model.safetensors")
    del state["head.bias"]
    save_file(state, folder / "model.safetensors")
    return "lacks 'head.bias', which the architecture in student.json has"


TAMPERED = {
    "code": _code,
    "pickle": _pickle,
    "shape": _shape,
    "target": _target,
    "trunk": _trunk,
    "nan": _nan,
    "missing": _missing,
}


@pytest.mark.parametrize("case", sorted(TAMPERED))
def test_a_tampered_student_directory_is_refused(world: dict[str, Path], tmp_path: Path, case: str) -> None:
    folder = _copy_student(world, tmp_path)
    fragment = TAMPERED[case](folder)
    with pytest.raises(SemvprError) as err:
        load(world, "plain", tmp_path / "cache", "mask=student", f"student.checkpoint={folder}")
    assert fragment in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("case", ["code", *(pytest.param(c, marks=pytest.mark.slow) for c in ("pickle", "shape"))])
def test_cli_refuses_a_tampered_student_directory_in_one_line(
    world: dict[str, Path], tmp_path: Path, case: str
) -> None:
    folder = _copy_student(world, tmp_path)
    fragment = TAMPERED[case](folder)
    proc = cli(tmp_path, f"ckpt={world['plain']}", *frames_args(world), "mask=student", f"student.checkpoint={folder}")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("semvpr: error: ") and fragment in lines[0], proc.stderr
    assert not (tmp_path / "cache").exists() or not list((tmp_path / "cache").glob("descriptors-*"))


def test_localize_and_the_hub_take_the_replacement(world: dict[str, Path], tmp_path: Path) -> None:
    from semvpr.hub import load_model
    from semvpr.localize import localize

    overrides = ["mask=student", f"student.checkpoint={world['student']}"]
    model = load_model(world["plain"], overrides=overrides)
    assert model.retriever.mask_source.student.trained_on.name == "camvid"
    cfg = config(
        *frames_args(world),
        f"+ckpt={world['plain']}",
        f"paths.cache_dir={tmp_path}",
        f"queries={world['frames'] / 'night'}",
        "top_k=1",
        *overrides,
        config_name="localize",
    )
    results = localize(cfg, {"mask", "student.checkpoint"})
    # Query frame i is database frame i's image: the nearest is itself, mask or not.
    assert [Path(r["matches"][0]["path"]).name for r in results] == [Path(r["query"]).name for r in results]


def test_espnetv2_replaces_the_mask_at_evaluation(world: dict[str, Path], tmp_path: Path) -> None:
    from semvpr.models.espnetv2 import ESPNetv2Segmentation
    from tests.helpers import write_espnetv2

    overrides = ["mask=teacher", "teacher=espnetv2", f"teacher.checkpoint={write_espnetv2(tmp_path / 'esp.pth')}"]
    own, _ = descriptors(world, "plain", tmp_path / "a")
    ours, retriever = descriptors(world, "plain", tmp_path / "b", *overrides, "teacher.inference_size=[32,64]")
    assert isinstance(retriever.mask_source.teacher.model, ESPNetv2Segmentation)
    assert retriever.mask_source.teacher.inference_size == (32, 64) and not np.allclose(ours, own)
    for name, value in checkpoint_state(world["plain"], "aggregator.").items():
        assert torch.equal(retriever.aggregator.state_dict()[name], value), name
    from semvpr.hub import load_model

    hub = load_model(world["plain"], overrides=[*overrides, "teacher.inference_size=[32,64]"])
    assert isinstance(hub.retriever.mask_source.teacher.model, ESPNetv2Segmentation)

"""A checkpoint is data: genuine ones load for every aggregator, mask and backbone; hostile ones run nothing."""

from __future__ import annotations

import copy
import os
import pickle
import re
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch
from omegaconf import OmegaConf

from semvpr.config.restore import load_retriever
from semvpr.core.checkpoint import read_weights
from semvpr.core.errors import SemvprError
from tests.helpers import REPO, tiny_config, write_checkpoint


@pytest.mark.parametrize(
    "filter_name,backbone",
    [
        ("none", "vgg16"),
        ("attention", "vgg16"),
        ("unet", "vgg16"),
        ("mask2former", "vgg16"),
        ("oracle", "vgg16"),
        ("unet", "resnet50"),
        ("mask2former", "resnet50"),
        ("none", "efficientnet_lite0"),
        ("unet", "efficientnet_lite0"),
    ],
)
def test_genuine_checkpoints_load(tmp_path: Path, filter_name: str, backbone: str) -> None:
    trained = tiny_config(tmp_path, f"filter={filter_name}", f"backbone={backbone}", "model.pca_dim=4", "seed=3")
    state = write_checkpoint(trained, tmp_path / "run.ckpt")
    # Eval's own config: the defaults (efficientnet_lite0, none, seed 0) and another dataset size.
    cfg = tiny_config(tmp_path, f"+ckpt={tmp_path / 'run.ckpt'}", "data.image_size=[48,64]", config_name="eval")
    retriever, merged = load_retriever(cfg)
    preset = tiny_config(tmp_path, f"filter={filter_name}")
    assert (merged.aggregator.name, merged.mask.name) == (preset.aggregator.name, preset.mask.name)
    assert (merged.backbone.name, merged.seed) == (backbone, 3)
    assert list(merged.data.image_size) == [48, 64] and merged.model.pca_dim == 4
    loaded = retriever.state_dict()
    assert loaded.keys() == state.keys() and all(torch.equal(loaded[k], state[k]) for k in state)


def _set(path: str, value: Any) -> Callable[[dict], None]:
    def edit(record: dict) -> None:
        *parents, leaf = path.split(".")
        node = record
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value

    return edit


@pytest.fixture(scope="module")
def genuine_record(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict]:
    tmp = tmp_path_factory.mktemp("genuine")
    write_checkpoint(tiny_config(tmp, "filter=none"), tmp / "run.ckpt")
    ckpt = torch.load(tmp / "run.ckpt", weights_only=True)
    return ckpt["state_dict"], ckpt["hyper_parameters"]


def _hostile(tmp_path: Path, genuine_record: tuple[dict, dict], edit: Callable[[dict], None]) -> Path:
    state, record = genuine_record
    record = copy.deepcopy(record)
    edit(record)
    path = tmp_path / "evil.ckpt"
    torch.save({"state_dict": state, "hyper_parameters": record}, path)
    return path


SENTINEL_TEXT = "untouched"


@pytest.mark.parametrize(
    "edit,message",
    [
        # A stored _target_ naming one of semvpr's own JSON writers (it overwrote a file before this change).
        (
            lambda s: _set("config.backbone", {"_target_": "semvpr.train.write_json", "path": s, "obj": "pwned"}),
            r"backbone\._target_ is refused",
        ),
        (lambda s: _set("config.aggregator._target_", "torch.save"), r"aggregator\._target_ is refused"),
        (lambda s: _set("config.teacher.checkpoint", "${oc.env:HOME}"), r"teacher\.checkpoint=.*interpolations"),
        (lambda s: _set("config.model.evil", 1), r"model\.evil is not a key"),
        (lambda s: _set("config.model.num_clusters", "32"), r"model\.num_clusters='32' has the wrong type"),
        (
            lambda s: _set("config.teacher.model", {"embed_dim": {"_target_": "numpy.save", "file": s}}),
            r"teacher\.model\.embed_dim is a mapping",
        ),
        (lambda s: _set("choices.backbone", "../../tmp/evil"), r"choices\.backbone='\.\./\.\./tmp/evil' is not one of"),
        (lambda s: _set("seed", "0"), r"seed='0' must be a whole number from 0"),
        (lambda s: _set("seed", 2**32), r"seed=4294967296 must be a whole number from 0 to 4294967295"),
        (lambda s: _set("seed", True), r"seed=True must be a whole number"),
        # A stored path redirected eval to load another directory as the teacher.
        (lambda s: _set("config.teacher.checkpoint", s), r"teacher\.checkpoint=.*names a local path"),
        (lambda s: _set("config.teacher.checkpoint", "../teachers/evil"), r"teacher\.checkpoint=.*names a local path"),
        (lambda s: _set("config.teacher.checkpoint", "~/evil"), r"teacher\.checkpoint=.*names a local path"),
    ],
)
def test_hostile_checkpoints_are_refused_before_anything_runs(
    tmp_path: Path, genuine_record: tuple[dict, dict], edit: Callable, message: str
) -> None:
    sentinel = tmp_path / "sentinel.json"
    sentinel.write_text(SENTINEL_TEXT)
    path = _hostile(tmp_path, genuine_record, edit(str(sentinel)))
    cfg = tiny_config(tmp_path, f"+ckpt={path}", config_name="eval")
    with pytest.raises(SemvprError, match=message) as err:
        load_retriever(cfg)
    assert "\n" not in str(err.value)
    assert sentinel.read_text() == SENTINEL_TEXT


def test_old_format_checkpoint_is_refused_with_how_to_fix(tmp_path: Path, genuine_record: tuple[dict, dict]) -> None:
    state, _ = genuine_record
    path = tmp_path / "old.ckpt"
    torch.save({"state_dict": state, "hyper_parameters": {"config": {"backbone": {"_target_": "x"}}}}, path)
    with pytest.raises(SemvprError, match="older semvpr.*retrain it"):
        load_retriever(tiny_config(tmp_path, f"+ckpt={path}", config_name="eval"))


def test_cli_refuses_a_hostile_checkpoint_with_one_line(tmp_path: Path, genuine_record: tuple[dict, dict]) -> None:
    sentinel = tmp_path / "sentinel.json"
    sentinel.write_text(SENTINEL_TEXT)
    path = _hostile(
        tmp_path,
        genuine_record,
        _set("config.backbone", {"_target_": "semvpr.train.write_json", "path": str(sentinel), "obj": 1}),
    )
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.eval",
            "experiment=tiny",
            f"paths.cache_dir={tmp_path}",
            f"ckpt={path}",
            f"hydra.run.dir={tmp_path / 'out'}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "_target_ is refused" in proc.stderr
    assert sentinel.read_text() == SENTINEL_TEXT


def test_filter_record_loads_as_the_presets_aggregator_and_mask(tmp_path: Path) -> None:
    trained = tiny_config(tmp_path, "filter=unet", "filter.weights=learned")
    state = write_checkpoint(trained, tmp_path / "new.ckpt")
    record = torch.load(tmp_path / "new.ckpt", weights_only=True)["hyper_parameters"]
    # The record as written when the filter bundled aggregator and mask.
    choices = {k: v for k, v in record["choices"].items() if k not in ("aggregator", "mask")}
    config = {k: v for k, v in record["config"].items() if k not in ("aggregator", "mask")}
    old = {
        **record,
        "choices": {**choices, "filter": "unet"},
        "config": {
            **config,
            "filter": {
                "name": "unet",
                "aggregator": {"num_clusters": 8, "num_shadows": 4},
                "init": "semantic",
                "mask": "student",
                "weights": "learned",
            },
        },
    }
    torch.save({"state_dict": state, "hyper_parameters": old}, tmp_path / "old.ckpt")
    retriever, merged = load_retriever(tiny_config(tmp_path, f"+ckpt={tmp_path / 'old.ckpt'}", config_name="eval"))
    assert (merged.aggregator.name, merged.mask.name, merged.mask.weights) == ("sral", "student", "learned")
    assert retriever.class_weights is not None


def test_a_format_2_record_with_a_model_group_loads_its_structure(tmp_path: Path) -> None:
    """Format 2 recorded the training protocol and the model's structure in one ``model`` group
    (``model=netvlad``); the structure (clusters, whitening, ...) is read, the protocol left out."""
    trained = tiny_config(tmp_path, "filter=attention", "model.pca_dim=8", "model.num_clusters=6")
    state = write_checkpoint(trained, tmp_path / "new.ckpt")
    record = torch.load(tmp_path / "new.ckpt", weights_only=True)["hyper_parameters"]
    assert record["format"] == 4 and "model" not in record["choices"]
    protocol = {"name": "netvlad", "margin": 0.1, "batch_size": 2, "positive_radius": 10.0, "class_weights": {}}
    old = {
        **record,
        "format": 2,
        "choices": {**record["choices"], "model": "netvlad"},
        "config": {**record["config"], "model": {**protocol, **record["config"]["model"]}},
    }
    old["config"]["model"]["class_weights"] = {"init_logit": 4.0, "lr": 0.05}
    torch.save({"state_dict": state, "hyper_parameters": old}, tmp_path / "old.ckpt")
    retriever, merged = load_retriever(tiny_config(tmp_path, f"+ckpt={tmp_path / 'old.ckpt'}", config_name="eval"))
    assert (merged.model.num_clusters, merged.model.pca_dim, retriever.descriptor_dim) == (6, 8, 8)
    assert "margin" not in merged.model and merged.recipe.name == "triplet"


#: The group's own keys, which format 3 recorded beside each component group's ``module`` node (the class's
#: values; a backbone's file also held its values beside the node, which repeated them).
FORMAT_3_BESIDE = {
    "backbone": ("name", "paper_train_from"),
    "aggregator": ("name", "baseline", "gsv"),
    "mask": ("name", "upper_bound", "weights"),
}


def _format_3(config: dict[str, Any]) -> dict[str, Any]:
    """A format-4 record's config as format 3 wrote it."""
    old = copy.deepcopy(config)
    for group, beside in FORMAT_3_BESIDE.items():
        values = {k: v for k, v in config[group].items() if k not in beside}
        if group != "backbone":
            old[group] = {k: v for k, v in config[group].items() if k in beside}
        old[group]["module"] = None if group == "mask" and config["mask"]["name"] == "none" else values
    return old


@pytest.mark.parametrize(
    "overrides",
    [
        ("aggregator=mixvpr", "aggregator.out_channels=24", "aggregator.out_rows=2", "mask=student"),
        ("aggregator=netvlad", "mask=none"),
    ],
)
def test_a_format_3_record_reads_its_module_nodes_as_the_groups_values(tmp_path: Path, overrides: tuple) -> None:
    """Format 3 recorded the backbone's, aggregator's and mask source's constructor values in a ``module`` node
    (a backbone's repeating the group's own; ``module: null`` for no mask); they load as the group's values:
    the same model, the same weights."""
    state = write_checkpoint(tiny_config(tmp_path, *overrides), tmp_path / "new.ckpt")
    record = torch.load(tmp_path / "new.ckpt", weights_only=True)["hyper_parameters"]
    old = {**record, "format": 3, "config": _format_3(record["config"])}
    assert "module" in old["config"]["aggregator"] and "module" not in record["config"]["aggregator"]
    torch.save({"state_dict": state, "hyper_parameters": old}, tmp_path / "old.ckpt")
    loaded = {}
    for name in ("new", "old"):
        cfg = tiny_config(tmp_path, f"+ckpt={tmp_path / f'{name}.ckpt'}", config_name="eval")
        retriever, merged = load_retriever(cfg)
        weights = retriever.state_dict()
        assert weights.keys() == state.keys() and all(torch.equal(weights[k], state[k]) for k in state)
        loaded[name] = {g: OmegaConf.to_container(merged[g], resolve=True) for g in FORMAT_3_BESIDE}
    assert loaded["old"] == loaded["new"] and "module" not in loaded["old"]["aggregator"]
    if "aggregator=mixvpr" in overrides:
        assert (loaded["old"]["aggregator"]["out_channels"], loaded["old"]["aggregator"]["grid"]) == (24, [4, 5])


@pytest.mark.parametrize(
    ("grid", "line"),
    [
        ("abc", r"^checkpoint .*: aggregator\.grid='abc': aggregator=mixvpr expects a list of whole numbers$"),
        ([4, 5, 6], r"^aggregator\.grid=\[4, 5, 6\] is not \[h, w\]"),  # read as 4 x 5 before
    ],
)
def test_a_recorded_grid_that_is_not_h_w_is_one_line(tmp_path: Path, grid: Any, line: str) -> None:
    """The grid a fixed-grid aggregator's file leaves null has no kind a record's value is checked against: the
    class's annotation, and MixVPR itself, check it."""
    state = write_checkpoint(tiny_config(tmp_path, "aggregator=mixvpr"), tmp_path / "run.ckpt")
    record = torch.load(tmp_path / "run.ckpt", weights_only=True)["hyper_parameters"]
    record["config"]["aggregator"]["grid"] = grid
    torch.save({"state_dict": state, "hyper_parameters": record}, tmp_path / "bad.ckpt")
    with pytest.raises(SemvprError, match=line):
        load_retriever(tiny_config(tmp_path, f"+ckpt={tmp_path / 'bad.ckpt'}", config_name="eval"))


def test_fixed_grid_aggregator_keeps_its_grid_at_another_image_size(tmp_path: Path) -> None:
    trained = tiny_config(tmp_path, "aggregator=mixvpr")
    state = write_checkpoint(trained, tmp_path / "run.ckpt")
    # Left null in the config, filled in from the backbone's grid at data.image_size, recorded.
    grid = torch.load(tmp_path / "run.ckpt", weights_only=True)["hyper_parameters"]["config"]["aggregator"]["grid"]
    assert trained.aggregator.grid is None and grid == [4, 5]  # 64 x 80 at stride 16
    cfg = tiny_config(tmp_path, f"+ckpt={tmp_path / 'run.ckpt'}", "data.image_size=[96,128]", config_name="eval")
    retriever, merged = load_retriever(cfg)
    assert list(merged.aggregator.grid) == [4, 5]
    assert all(torch.equal(retriever.state_dict()[k], state[k]) for k in state)
    with torch.no_grad():  # a larger feature grid than trained: pooled to the recorded one
        assert retriever(torch.rand(2, 3, 96, 128)).shape == (2, retriever.aggregator.output_dim)


def test_a_stored_hugging_face_id_or_the_invocations_own_path_passes(tmp_path: Path) -> None:
    from semvpr.config.record import model_config, record_of

    record = record_of(tiny_config(tmp_path))
    record["config"]["teacher"]["checkpoint"] = "facebook/mask2former-swin-large-cityscapes-semantic"
    assert model_config(record, tiny_config(tmp_path)).teacher.checkpoint.startswith("facebook/")
    record["config"]["teacher"]["checkpoint"] = str(tmp_path)
    given = tiny_config(tmp_path, f"teacher.checkpoint={tmp_path}")
    assert model_config(record, given).teacher.checkpoint == str(tmp_path)


@pytest.mark.parametrize(
    ("damage", "fault"),
    [
        ("nan", "is not finite"),  # it evaluated to R@N = 0 with exit 0
        ("complex", r"is complex \(torch.complex64\)"),  # cast to real with a warning, exit 0
        ("strides", r"has shape \(1000000, 100000\) \(100,000,000,000 values\) from 1 stored"),  # 400 GB to check
        ("key", "is not named by a string"),  # an AttributeError traceback
    ],
)
def test_a_checkpoint_with_damaged_weights_is_refused(
    tmp_path: Path, genuine_record: tuple[dict, dict], damage: str, fault: str
) -> None:
    state, record = genuine_record
    state = dict(state)
    name: object = next(k for k, v in state.items() if v.is_floating_point())
    value = state[name]
    if damage == "nan":
        state[name] = value.clone().fill_(float("nan"))
    elif damage == "complex":
        state[name] = value.to(torch.complex64)
    elif damage == "strides":
        state[name] = torch.zeros(1).expand(10**6, 10**5)
    else:
        name = 7
        state[name] = value
    torch.save({"state_dict": state, "hyper_parameters": record}, tmp_path / "bad.ckpt")
    with pytest.raises(SemvprError, match=f"weight {name!r} {fault}; the checkpoint is damaged"):
        load_retriever(tiny_config(tmp_path, f"+ckpt={tmp_path / 'bad.ckpt'}", config_name="eval"))


@pytest.mark.parametrize(
    ("edit", "named"),
    [
        ("drop", r"no weight '{key}', which the model needs$"),
        ("add", r"key 'aggregator\.extra' is not part of the model$"),
        ("reshape", r"'{key}' has shape \(3,\), the model needs \("),
        ("drop all of it", r"no weight '{key}', which the model needs \(and [0-9]+ more\)$"),
        # Cast without a word, they evaluated "ok": integers or booleans for float weights, float64 values
        # finite in the file and infinite in float32 (refused only after the whole trunk pass).
        ("int64", r"'{key}' is int64, where the model holds float32 weights$"),
        ("bool", r"'{key}' is bool, where the model holds float32 weights$"),
        ("float64 beyond float32", r"'{key}' holds 1e\+39, beyond float32's range$"),
    ],
)
def test_weights_that_do_not_fit_the_recorded_model_name_the_key(
    tmp_path: Path, genuine_record: tuple[dict, dict], edit: str, named: str
) -> None:
    """torch's own message opens with a line that names no key ("Error(s) in loading state_dict")."""
    state, record = genuine_record
    state = dict(state)
    key = sorted(k for k in state if k.startswith("aggregator."))[0]
    if edit == "drop":
        del state[key]
    elif edit == "add":
        state["aggregator.extra"] = torch.zeros(2)
    elif edit == "reshape":
        state[key] = torch.zeros(3)
    elif edit in ("int64", "bool"):
        state[key] = state[key].to(getattr(torch, edit))
    elif edit.startswith("float64"):
        state[key] = state[key].double().clone()
        state[key].view(-1)[0] = 1e39
    else:
        state = {k: v for k, v in state.items() if not k.startswith("aggregator.")}
    torch.save({"state_dict": state, "hyper_parameters": record}, tmp_path / "misfit.ckpt")
    with pytest.raises(
        SemvprError, match=r"misfit\.ckpt does not fit backbone=.*: " + named.format(key=re.escape(key))
    ):
        load_retriever(tiny_config(tmp_path, f"+ckpt={tmp_path / 'misfit.ckpt'}", config_name="eval"))


def test_a_run_directory_or_a_missing_file_as_ckpt_is_one_line_naming_the_file(tmp_path: Path) -> None:
    """A run directory given as ``ckpt`` names the checkpoints in it; another directory or a missing file says which."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    with pytest.raises(SemvprError, match=r"run is a directory, not a file \(a run writes"):
        read_weights(run)
    (run / "checkpoints" / "tested.ckpt").write_bytes(b"")
    with pytest.raises(
        SemvprError, match=rf"run is a run directory; name a file in it: {run}/checkpoints/tested.ckpt$"
    ):
        read_weights(run)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"")
    with pytest.raises(SemvprError, match=r"name a file in it: .*/tested.ckpt or .*/checkpoints/last.ckpt$"):
        read_weights(run)
    with pytest.raises(SemvprError, match=r"absent.ckpt not found"):
        read_weights(tmp_path / "absent.ckpt")
    with pytest.raises(SemvprError, match=r"^backbone weights .*run is a directory, not a file$"):
        read_weights(run, what="backbone weights")
    # A segmenter semvpr.segment saved is no checkpoint: it masks one (was 'a directory, not a file').
    for kind, marker in (("student", "student.json"), ("teacher", "semvpr.json"), ("teacher", "config.json")):
        folder = tmp_path / f"{kind}-{marker}"
        folder.mkdir()
        (folder / marker).write_text("{}")
        line = rf"{folder} is a saved {kind} \(semvpr.segment\), not a checkpoint: .* {kind}.checkpoint={folder}$"
        with pytest.raises(SemvprError, match=line):
            read_weights(folder)


def test_checkpoints_are_staged_beside_their_target_never_in_tmpdir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The run's Trainer writes checkpoints through RunCheckpointIO: every file it creates or renames lies in
    the checkpoint's own folder (Lightning's own writer stages them in $TMPDIR first)."""
    import os
    import shutil
    import tempfile

    from semvpr.config.build import build_trainer
    from semvpr.config.plan import job_plan
    from semvpr.core.checkpoint import RunCheckpointIO

    tmpdir = tmp_path / "tmpdir"
    tmpdir.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmpdir))
    cfg = tiny_config(tmp_path / "cache")
    trainer = build_trainer(job_plan(cfg), tmp_path / "run", [])
    io = trainer.strategy.checkpoint_io
    assert isinstance(io, RunCheckpointIO)
    moves: list[str] = []
    for module, name in ((os, "replace"), (os, "rename"), (shutil, "move")):
        real = getattr(module, name)
        monkeypatch.setattr(
            module, name, lambda src, dst, *a, real=real, **k: (moves.append(str(src)), real(src, dst, *a, **k))[1]
        )
    target = tmp_path / "run" / "checkpoints" / "last.ckpt"
    io.save_checkpoint({"state_dict": {"w": torch.ones(3)}, "epoch": 1}, target)
    assert torch.load(target, weights_only=True)["epoch"] == 1
    assert moves and all(Path(m).parent == target.parent for m in moves), moves
    assert list(tmpdir.iterdir()) == [] and sorted(p.name for p in target.parent.iterdir()) == ["last.ckpt"]


@pytest.mark.parametrize(
    ("content", "line"),
    [
        (b"hello", "not a torch file (neither the zip archive torch.save writes nor a pickle of protocol 2 or later)"),
        (b"", "not a torch file"),
        (pickle.dumps({"a": 1}, protocol=0), "not a torch file"),
        (pickle.dumps({"a": 1}, protocol=5), "(UnpicklingError: the weights-only reader cannot read it: Unsupported"),
        ("truncated", "is not a readable checkpoint (RuntimeError: "),
    ],
)
def test_a_file_torch_cannot_read_is_one_line_without_torchs_advice(
    tmp_path: Path, content: bytes | str, line: str
) -> None:
    """Not torch's advice to load with weights_only=False (semvpr never does), nor its pickle-protocol warning."""
    path = tmp_path / "f.pth"
    if content == "truncated":
        torch.save({"w": torch.zeros(100)}, path)
        path.write_bytes(path.read_bytes()[:200])
    else:
        path.write_bytes(content)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SemvprError) as err:
            read_weights(path)
    message = str(err.value)
    assert message.startswith(f"{path} is not a readable checkpoint") and line in message, message
    assert "\n" not in message and "weights_only" not in message


class _Calls:
    """Pickled as a call of ``function`` (a global of ``os``, ``posix``, ``sys``...): loading it unsafely runs it."""

    def __init__(self, function: object) -> None:
        self.function = function

    def __reduce__(self) -> tuple[object, tuple[str, ...]]:
        return (self.function, ("true",))


@pytest.mark.parametrize("function", [os.system, os.getcwd, sys.exit])
def test_a_pickled_call_of_a_blocked_module_is_named_and_no_unsafe_load_is_advised(
    tmp_path: Path, function: object
) -> None:
    """torch refuses globals of os, posix, sys and nt with its own line, which advises re-running the load with
    weights_only=False."""
    torch.save({"state_dict": {}, "hook": _Calls(function)}, tmp_path / "calls.ckpt")
    with pytest.raises(SemvprError) as err:
        read_weights(tmp_path / "calls.ckpt")
    line = str(err.value)
    module, name = function.__module__, function.__name__  # type: ignore[attr-defined]
    assert f"it pickles an object ({'posix' if module == 'os' else module}.{name})" in line, line
    assert "weights_only" not in line and "\n" not in line


def test_a_fifo_or_a_device_as_a_checkpoint_is_named_as_what_it_is(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "pipe.ckpt")
    with pytest.raises(SemvprError, match=r"pipe\.ckpt is not a regular file: a FIFO \(named pipe\)$"):
        read_weights(tmp_path / "pipe.ckpt")
    with pytest.raises(SemvprError, match=r"checkpoint /dev/zero is not a regular file: a character device$"):
        read_weights("/dev/zero")


def test_a_model_value_eval_cannot_honour_is_refused_and_the_describing_batch_is_taken(tmp_path: Path) -> None:
    """``model.pca_dim=64`` at eval gave the checkpoint's own descriptors (no whitening) with no word."""
    write_checkpoint(tiny_config(tmp_path), tmp_path / "t.ckpt")

    def load(override: str) -> Any:
        key = override.partition("=")[0]
        return load_retriever(
            tiny_config(tmp_path, f"+ckpt={tmp_path / 't.ckpt'}", override, config_name="eval"), {key}
        )

    for override, own in (("model.pca_dim=16", "null"), ("model.num_shadows=2", "4")):
        key = override.partition("=")[0]
        with pytest.raises(SemvprError, match=rf"t\.ckpt defines {re.escape(key)}={own}, which an evaluation cannot"):
            load(override)
    assert load("model.eval_batch_size=7")[1].model.eval_batch_size == 7
    assert load("model.num_shadows=4")[1].model.num_shadows == 4  # the model's own value: nothing to change

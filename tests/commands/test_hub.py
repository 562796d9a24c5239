"""torch.hub.load(<repo>, "semvpr", ckpt=..., source="local"): a checkpoint usable by others' scripts."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from semvpr.core.errors import SemvprError
from tests.helpers import REPO, make_folder, tiny_config, write_checkpoint


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("hub")
    write_checkpoint(tiny_config(tmp, "filter=attention"), tmp / "tested.ckpt")
    return tmp / "tested.ckpt"


def test_hub_model_takes_normalised_images_and_gives_unit_descriptors(checkpoint: Path) -> None:
    model = torch.hub.load(str(REPO), "semvpr", ckpt=str(checkpoint), source="local", image_size=[32, 48])
    rng = np.random.default_rng(0)
    images = [Image.fromarray(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)) for _ in range(3)]
    batch = torch.stack([model.transform(im) for im in images])
    assert batch.shape == (3, 3, 32, 48)
    # The transform is ImageNet normalisation: channel 0 of a pixel is (v/255 - 0.485) / 0.229.
    resized = images[0].resize((48, 32), Image.BILINEAR)
    assert abs(float(batch[0, 0, 5, 7]) - (np.asarray(resized)[5, 7, 0] / 255 - 0.485) / 0.229) < 0.1
    desc = model(batch)
    assert desc.shape == (3, model.feature_dim) and desc.dtype == torch.float32
    np.testing.assert_allclose(desc.norm(dim=1).numpy(), 1.0, atol=1e-5)


def eval_descriptors(tmp_path: Path, ckpt: Path, given: list[str]) -> list[np.ndarray]:
    """``semvpr.eval``'s descriptors (database and queries, from its descriptor cache) of ``ckpt`` with ``given``."""
    from semvpr.eval import evaluate_checkpoint

    cfg = tiny_config(tmp_path / "cache", f"+ckpt={ckpt}", *given, config_name="eval")
    evaluate_checkpoint(cfg, {o.split("=", 1)[0].lstrip("+") for o in given})
    return [np.load(f) for f in sorted((tmp_path / "cache").glob("descriptors-*/descriptors.npy"))]


@pytest.mark.parametrize("release", [False, True], ids=["checkpoint", "release"])
def test_hub_gives_evals_descriptors_of_the_same_images(checkpoint: Path, tmp_path: Path, release: bool) -> None:
    """The hub computes in eval's arithmetic for the same model and overrides (the job's bf16 for a semvpr
    checkpoint, fp32 for a release, bf16 when asked) and its transform resizes as eval's loader does (PIL's
    bilinear; BoQ's bicubic on the tensor), so the same image files give eval's descriptors."""
    from semvpr.hub import load_model
    from tests.models.test_released import boq_model, save_state

    if release:
        save_state(boq_model(), tmp_path / "b.pth")
        ckpt, precisions = tmp_path / "b.pth", [[], ["trainer.precision=bf16-mixed"]]
    else:
        ckpt, precisions = checkpoint, [[]]
    root = make_folder(tmp_path / "places")
    files = sorted((root / "images" / "test" / "database").iterdir())
    for asked in precisions:
        given = ["experiment=tiny", "data=folder", f"data.root={root}", "data.image_size=[32,48]", *asked]
        shutil.rmtree(tmp_path / "cache", ignore_errors=True)
        expected = eval_descriptors(tmp_path, ckpt, [*given, "data.num_workers=0"])
        model = load_model(ckpt, [32, 48], overrides=[*given, f"paths.cache_dir={tmp_path / 'cache'}"])
        assert model.arithmetic.precision == ("32-true" if release and not asked else "bf16-mixed")
        desc = model(torch.stack([model.transform(Image.open(f)) for f in files])).numpy()
        assert len(expected) == 2
        for cached in expected:
            # The hub un-normalises its input (rounding of 1e-7), which an fp32 trunk output can carry over a bf16
            # rounding step of the trunk cache: 2e-5 here. The old hub ran a bf16 job's model in fp32: 1.6e-3.
            np.testing.assert_allclose(desc, cached, rtol=0, atol=5e-5)


def test_hub_refuses_images_on_another_device_in_one_line(checkpoint: Path) -> None:
    from semvpr.hub import load_model

    model = load_model(checkpoint)
    with pytest.raises(SemvprError, match=r"^images are on meta, the model on cpu: move the images there") as err:
        model(torch.empty(2, 3, 32, 48, device="meta"))
    assert "\n" not in str(err.value)
    assert {p.device.type for p in model.parameters()} == {"cpu"}  # the model stays where it is


def test_hub_refuses_what_eval_refuses(checkpoint: Path, tmp_path: Path) -> None:
    ckpt = torch.load(checkpoint, weights_only=True)
    ckpt["hyper_parameters"]["choices"]["backbone"] = "../../evil"
    torch.save(ckpt, tmp_path / "tampered.ckpt")
    with pytest.raises(
        SemvprError, match=r"choices.backbone='../../evil' is not one of the project's backbone configs"
    ):
        torch.hub.load(str(REPO), "semvpr", ckpt=str(tmp_path / "tampered.ckpt"), source="local")
    with pytest.raises(SemvprError, match=r"checkpoint .*missing.ckpt not found"):
        torch.hub.load(str(REPO), "semvpr", ckpt=str(tmp_path / "missing.ckpt"), source="local")
    # Weights eval refuses at load, and weights whose descriptors overflow (eval refuses them before scoring;
    # the hub returned NaN descriptors).
    key = next(k for k, v in ckpt["state_dict"].items() if k.startswith("aggregator.") and v.ndim >= 2)
    weight = torch.load(checkpoint, weights_only=True)["state_dict"][key]
    for name, value, line in (
        ("wide", weight.double().fill_(1e39), rf"'{key}' holds 1e\+39, beyond float32's range"),
        ("huge", torch.full_like(weight, 3e38), r"the descriptors of these images are not finite"),
    ):
        damaged = torch.load(checkpoint, weights_only=True)
        damaged["state_dict"][key] = value
        torch.save(damaged, tmp_path / f"{name}.ckpt")
        with pytest.raises(SemvprError, match=line):
            model = torch.hub.load(str(REPO), "semvpr", ckpt=str(tmp_path / f"{name}.ckpt"), source="local")
            model(torch.rand(2, 3, 64, 80))


@pytest.mark.parametrize(
    ("ckpt", "overrides", "line"),
    [
        ("", [], r"^ckpt='' names no file"),  # it said "checkpoint . is a directory"
        ("none", "aggregator=gem", r"^overrides='aggregator=gem' is one string; pass a list"),  # parsed per letter
        ("none", ["+model.fooo=1"], r"^model\.fooo is not a setting of the project's config"),  # read by nothing
        ("none", ["data.test._target_=os.getcwd"], r"the key _target_ is refused"),
        # The setting given, not the teacher's key that interpolates it.
        ("none", ["data.image_size=[0,3]"], r"^data\.image_size\[0\]=0 must be a whole number"),
    ],
)
def test_hub_checks_its_arguments_as_the_cli_does(ckpt: str, overrides: object, line: str) -> None:
    from semvpr.hub import load_model

    with pytest.raises(SemvprError, match=line):
        load_model(ckpt, overrides=overrides)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("image_size", "line"),
    [([0, 0], r"image_size=\[0, 0\] is not a size"), ("224", "image_size='224' is not a size"), ([1, 2, 3], "is not")],
)
def test_hub_refuses_an_image_size_resize_would_misread(checkpoint: Path, image_size: object, line: str) -> None:
    from semvpr.hub import load_model

    with pytest.raises(SemvprError, match=line):
        load_model(checkpoint, image_size=image_size)  # type: ignore[arg-type]


def test_hub_model_refuses_images_it_would_misread_and_takes_any_float_batch(checkpoint: Path) -> None:
    from semvpr.hub import load_model

    model = load_model(checkpoint, overrides=None)
    images = torch.rand(2, 3, 32, 48)
    for bad, line in (
        (images[:, :1], r"a batch \(B, 3, H, W\), got \(2, 1, 32, 48\)"),  # broadcast to 3 channels before
        (images[0], r"got \(3, 32, 48\)"),
        ((images * 255).to(torch.uint8), "floats normalised .* got torch.uint8"),  # read as normalised values before
    ):
        with pytest.raises(SemvprError, match=line):
            model(bad)
    torch.testing.assert_close(model(images.double()), model(images))  # was a dtype RuntimeError
    assert model(images[:0]).shape == (0, model.feature_dim)  # was a reshape RuntimeError


def test_hub_transform_reads_any_8_bit_pil_image_as_semvpr_reads_image_files(checkpoint: Path, tmp_path: Path) -> None:
    """Grey, palette, RGBA and CMYK images (what Image.open gives for many real files) become the RGB tensor
    semvpr.eval's image reader makes of the same file; a 16-bit image is refused in the reader's line."""
    from semvpr.data.images import load_image
    from semvpr.hub import load_model

    model = load_model(checkpoint, image_size=[32, 48])
    rng = np.random.default_rng(0)
    rgb = Image.fromarray(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    mean, std = torch.tensor([0.485, 0.456, 0.406]).view(3, 1, 1), torch.tensor([0.229, 0.224, 0.225]).view(3, 1, 1)
    for mode, suffix in (("L", "png"), ("P", "png"), ("RGBA", "png"), ("CMYK", "jpg"), ("RGB", "png")):
        path = tmp_path / f"{mode}.{suffix}"
        rgb.convert(mode).save(path)
        with Image.open(path) as image:
            assert image.mode == mode
            tensor = model.transform(image)  # a channel-count RuntimeError (or 1-channel tensor) before
        assert tensor.shape == (3, 32, 48), mode
        torch.testing.assert_close(tensor * std + mean, load_image(path, [32, 48]), rtol=0, atol=1e-5)
    deep = tmp_path / "deep.png"
    Image.fromarray(rng.integers(0, 65535, (60, 80), dtype=np.uint16)).save(deep)  # read as values up to 65535 before
    with Image.open(deep) as image, pytest.raises(SemvprError, match="16-bit or float pixels"):
        model.transform(image)


@pytest.mark.parametrize("cast", ["half", "bfloat16", "double"])
def test_hub_model_with_cast_weights_is_refused_in_one_line_and_float_restores_it(checkpoint: Path, cast: str) -> None:
    """The model keeps float32 weights and computes in eval's precision for it (model.arithmetic); weights cast with
    .half() / .bfloat16() / .double() met float activations in the first layer (a dtype RuntimeError)."""
    from semvpr.hub import load_model

    model = load_model(checkpoint)
    images = torch.rand(2, 3, 32, 48)
    expected = model(images)
    getattr(model, cast)()
    line = r"weights are torch\.\w+; it keeps them float32 and computes in semvpr\.eval's precision for it \(bf16"
    with pytest.raises(SemvprError, match=line + r".* model\.float\(\)"):
        model(images)
    restored = model.float()(images)  # a float64 round trip is exact; 16 bits rounded the weights
    torch.testing.assert_close(restored, expected, rtol=0, atol=0 if cast == "double" else 0.05)


def test_hub_device_is_named_as_the_commands_name_it(checkpoint: Path) -> None:
    """device= takes what eval's device= takes, refused in the same line (torch's own errors before)."""
    from semvpr.hub import load_model

    for device, line in (("mps", r"device='mps' must be auto, cpu, cuda or cuda:N"), ("cuda:x", r"cuda:x")):
        with pytest.raises(SemvprError, match=line):
            load_model(checkpoint, device=device)
    if not torch.cuda.is_available():
        with pytest.raises(SemvprError, match=r"^cuda asks for a CUDA GPU and none is visible here"):
            load_model(checkpoint, device="cuda")  # was "Found no NVIDIA driver on your system ..."
    model = load_model(checkpoint, device="auto")
    assert model.mean.device == (torch.device("cuda", 0) if torch.cuda.is_available() else torch.device("cpu"))


@pytest.mark.parametrize("folder", ["a,b", "a=b", "it's"])
def test_hub_paths_with_override_syntax_load(tmp_path: Path, checkpoint: Path, folder: str) -> None:
    path = tmp_path / folder / "tested.ckpt"
    path.parent.mkdir()
    shutil.copy(checkpoint, path)
    model = torch.hub.load(str(REPO), "semvpr", ckpt=str(path), source="local")
    assert model.feature_dim > 0


def test_hub_loads_the_file_named_not_an_interpolation_of_it(
    tmp_path: Path, checkpoint: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from semvpr.core.errors import SemvprError

    named = tmp_path / "${oc.env:HUBX}" / "tested.ckpt"
    named.parent.mkdir()
    named.touch()  # the file named is empty; an interpolation would have loaded another
    (tmp_path / "other").mkdir()
    shutil.copy(checkpoint, tmp_path / "other" / "tested.ckpt")
    monkeypatch.setenv("HUBX", "other")
    with pytest.raises(SemvprError, match=r"\$\{oc\.env:HUBX\}/tested\.ckpt is not a readable checkpoint"):
        torch.hub.load(str(REPO), "semvpr", ckpt=str(named), source="local")

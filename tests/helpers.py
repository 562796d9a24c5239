"""Test helpers: the project's Hydra config (with the tiny SynthCity preset), an untrained checkpoint, and
the small datasets, lists and ground-truth files the tests write in each reader's layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.io
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig
from PIL import Image

from semvpr.data.places import DBSTRUCT_FIELDS

#: The checkout the tests run from.
REPO = Path(__file__).resolve().parents[1]
CONF_DIR = str(REPO / "conf")
#: ../shared/realdata beside the checkout (or beside the folder of worktrees); optional tests skip without it.
REALDATA = next(
    (p / "shared" / "realdata" for p in REPO.parents[:2] if (p / "shared" / "realdata").is_dir()),
    REPO.parent / "shared" / "realdata",
)
#: Small images for evaluation tests (overrides of a place set's config).
EVAL_SIZE = ["data.image_size=[32,48]", "data.num_workers=0"]


def tiny_config(cache_dir: Path, *overrides: str, config_name: str = "train") -> DictConfig:
    """The train config on the tiny preset, caching into ``cache_dir``."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(
            config_name=config_name, overrides=["experiment=tiny", f"paths.cache_dir={cache_dir}", *overrides]
        )


def config(*overrides: str, config_name: str = "train") -> DictConfig:
    """The project's config with these overrides."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides))


def write_checkpoint(cfg: DictConfig, path: Path) -> dict[str, torch.Tensor]:
    """Write an untrained model's checkpoint as a run does (Lightning's state_dict + hyper_parameters)."""
    from semvpr.config.build import build_backbone, build_mask_source, build_retriever
    from semvpr.config.plan import mask_plan, settings_of

    backbone = build_backbone(cfg.backbone, cfg.seed)
    retriever = build_retriever(settings_of(cfg), backbone, build_mask_source(mask_plan(cfg), backbone))
    torch.save({"state_dict": retriever.state_dict(), "hyper_parameters": dict(retriever.hparams), "epoch": 0}, path)
    return retriever.state_dict()


def record_first_unit_batches(backbone) -> list[int]:
    """The batch size of every pass through a backbone's first unit, appended as they happen."""
    seen: list[int] = []
    backbone.units[0].register_forward_hook(lambda _m, args, _out: seen.append(args[0].shape[0]))
    return seen


def mapped_file(address: int) -> Path | None:
    """The file whose memory map holds this address (``/proc/self/maps``), None where it is anonymous memory (the
    heap, an anonymous mapping): where a tensor's or array's data lives (``tensor.data_ptr()``,
    ``array.ctypes.data``)."""
    with open("/proc/self/maps") as maps:
        for line in maps:
            fields = line.split(maxsplit=5)
            start, end = (int(v, 16) for v in fields[0].split("-"))
            if start <= address < end:
                named = len(fields) == 6 and fields[4] != "0" and fields[5].startswith("/")
                return Path(fields[5].strip()) if named else None
    raise AssertionError(f"address {address:#x} is not mapped in this process")


# ---------------------------------------------------------------- data fixtures the tests write


def write_image(path: Path, seed: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.random.default_rng(seed).integers(0, 255, (48, 64, 3), dtype=np.uint8)).save(path)


def place_utm(i: int) -> tuple[float, float]:
    return 585000.0 + 100.0 * i, 4477000.0


def make_folder(root: Path, n: int = 6) -> Path:
    """@UTM@ layout; query i is database image i again (same place, same pixels)."""
    for i in range(n):
        e, north = place_utm(i)
        name = f"@{e:.2f}@{north:.2f}@17@T@@@@@@@@@@@.jpg"
        write_image(root / "images" / "test" / "database" / name, i)
        write_image(root / "images" / "test" / "queries" / name, i)
    return root


def write_pitts_mat(
    path: Path, which: str, db: list[str], q: list[str], db_utm: list | None = None, q_utm: list | None = None
) -> None:
    """A Pitts/Tokyo dbStruct .mat (fields in MATLAB's order); place i at place_utm(i) unless given."""
    utm_db = np.array(db_utm or [place_utm(i) for i in range(len(db))]).T
    utm_q = np.array(q_utm or [place_utm(i) for i in range(len(q))]).T
    fields = [
        ("whichSet", which),
        ("dbImageFns", np.array(db, dtype=object)[:, None]),
        ("utmDb", utm_db),
        ("qImageFns", np.array(q, dtype=object)[:, None]),
        ("utmQ", utm_q),
        ("numImages", len(db)),
        ("numQueries", len(q)),
        ("posDistThr", 25),
        ("posDistSqThr", 625),
        ("nonTrivPosDistSqThr", 100),
    ]
    record = np.empty((1, 1), dtype=[(name, object) for name, _ in fields])
    for name, value in fields:
        record[0, 0][name] = value
    path.parent.mkdir(parents=True, exist_ok=True)
    scipy.io.savemat(path, {"dbStruct": record})


def write_jpg(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (8, 6), (120, 30, 200)).save(path)


def write_dbstruct(
    path: Path, db_names: list[str], db_utm: np.ndarray, q_names: list[str], q_utm: np.ndarray, drop: str | None = None
) -> None:
    """A dbStruct .mat as MATLAB writes it: one struct, fields in the Pitts order."""
    values = {
        "whichSet": "test",
        "dbImageFns": db_names,
        "utmDb": db_utm.T,
        "qImageFns": q_names,
        "utmQ": q_utm.T,
        "numImages": len(db_names),
        "numQueries": len(q_names),
        "posDistThr": 25.0,
        "posDistSqThr": 625.0,
        "nonTrivPosDistSqThr": 100.0,
    }
    fields = [f for f in DBSTRUCT_FIELDS if f != drop]
    struct = np.empty((1, 1), dtype=[(f, object) for f in fields])
    for f in fields:
        v = values[f]
        if isinstance(v, list):  # cell array N×1 of char arrays
            cell = np.empty((len(v), 1), dtype=object)
            for i, s in enumerate(v):
                cell[i, 0] = np.array([s])
            v = cell
        struct[0, 0][f] = v
    scipy.io.savemat(str(path), {"dbStruct": struct})


def write_msls_side(
    folder: Path, rows: list[tuple[str, float, float, bool, bool]], columns: str = "easting,northing"
) -> None:
    """One side of a city in the official MSLS layout (mapillary_sls README): postprocessed.csv with
    UTMs, raw.csv with the panorama flag, subtask_index.csv, seq_info.csv, all indexed by frame.
    A row is (key, easting, northing, is_panorama, in the 'all' subtask)."""
    folder.mkdir(parents=True, exist_ok=True)
    post = [f",key,utm_zone,{columns},night,control_panel,view_direction,unique_cluster"]
    post += [f"{i},{k},32U,{e},{n},False,False,Forward,{i}" for i, (k, e, n, _, _) in enumerate(rows)]
    raw = [",key,lon,lat,ca,captured_at,pano"]
    raw += [f"{i},{k},12.5,55.6,90.0,1500000000000,{pano}" for i, (k, _, _, pano, _) in enumerate(rows)]
    sub = [",key,all,s2w,w2s,o2n,n2o,d2n,n2d"]
    sub += [f"{i},{k},{all_},False,False,False,False,False,False" for i, (k, _, _, _, all_) in enumerate(rows)]
    seq = [",key,frame_number,sequence_key"] + [f"{i},{k},{i},seq0" for i, (k, *_) in enumerate(rows)]
    for name, lines in (("postprocessed", post), ("raw", raw), ("subtask_index", sub), ("seq_info", seq)):
        (folder / f"{name}.csv").write_text("\n".join(lines) + "\n")
    (folder / "images").mkdir(exist_ok=True)


def object_array(rows: list[list[int]]) -> np.ndarray:
    out = np.empty(len(rows), dtype=object)
    for i, row in enumerate(rows):
        out[i] = np.array(row, dtype=np.int64)
    return out


def write_lists(gt_dir: Path, set_name: str, db: list[str], q: list[str], gt: np.ndarray) -> None:
    gt_dir.mkdir(parents=True, exist_ok=True)
    np.save(gt_dir / f"{set_name}_dbImages.npy", np.array(db))
    np.save(gt_dir / f"{set_name}_qImages.npy", np.array(q))
    np.save(gt_dir / f"{set_name}_gt.npy", gt, allow_pickle=True)


def same_images_as_lists(root: Path) -> tuple[list[str], list[str]]:
    """The database and query images of a test_eval @UTM@ folder, relative to it (query i = database i)."""
    names = sorted(p.name for p in (root / "images" / "test" / "database").iterdir())
    return [f"images/test/database/{n}" for n in names], [f"images/test/queries/{n}" for n in names]


#: The size CountingTeacher expects its images at.
LABEL_SIZE = (16, 20)


class CountingTeacher:
    """Labels pixels by brightness (road 0 / car 13) and counts the images it saw; can fail on cue."""

    device = torch.device("cpu")

    def __init__(self, fail_after: int | None = None, teacher_key: str = "teacher-abc") -> None:
        self.seen = 0
        self.fail_after = fail_after
        self.teacher_key = teacher_key

    def predict_train_ids(self, images: torch.Tensor) -> torch.Tensor:
        if self.fail_after is not None and self.seen + len(images) > self.fail_after:
            raise KeyboardInterrupt("simulated kill")
        self.seen += len(images)
        assert images.shape[-2:] == LABEL_SIZE
        return torch.where(images.mean(1) > 0.5, 13, 0).long()


def write_msls_cities(root: Path) -> Path:
    """An MSLS tree: cph and sf (val), london and zurich (train), miami (official test, no ground truth)."""
    tv = root / "train_val"
    write_msls_side(
        tv / "cph" / "database",
        [("c_db0", 100.0, 0.0, False, True), ("c_db1", 300.0, 0.0, False, True), ("c_pano", 100.0, 1.0, True, True)],
    )
    write_msls_side(tv / "cph" / "query", [("c_q0", 105.0, 0.0, False, True), ("c_q_other", 300.0, 2.0, False, False)])
    # Same UTM numbers as cph, in another zone.
    write_msls_side(
        tv / "london" / "database", [("l_db0", 100.0, 0.0, False, True), ("l_pano", 100.0, 0.0, True, True)]
    )
    write_msls_side(tv / "london" / "query", [("l_q0", 101.0, 0.0, False, True), ("l_qpano", 101.0, 0.0, True, True)])
    write_msls_side(tv / "sf" / "database", [("s_db0", 5.0, 5.0, False, True)])
    write_msls_side(tv / "sf" / "query", [("s_q0", 5.0, 6.0, False, True)])
    # A training city held out for epoch selection (subtask flags False: selection does not filter).
    write_msls_side(tv / "zurich" / "database", [("z_db0", 7.0, 7.0, False, False)])
    write_msls_side(tv / "zurich" / "query", [("z_q0", 7.0, 8.0, False, False)])
    # An official test city: images and subtask index only, no ground truth.
    for side in ("database", "query"):
        folder = root / "test" / "miami" / side
        folder.mkdir(parents=True)
        (folder / "subtask_index.csv").write_text(",key,all\n0,m0,True\n")
    return root


def write_msls_test_ground_truth(root: Path) -> Path:
    """The official test city miami of ``write_msls_cities(root)`` with its ground truth beside its images:
    postprocessed.csv and the subtask index, no raw.csv (the test release has none). Its database holds a
    panorama in the 'all' subtask (m_db0) and a frame outside it; its queries one in it (m_q0, 2 m from
    m_db0) and one outside."""
    miami = root / "test" / "miami"
    for side, rows in (
        ("database", [("m_db0", 10.0, 0.0, True, True), ("m_db1", 500.0, 0.0, False, False)]),
        ("query", [("m_q0", 12.0, 0.0, False, True), ("m_q_other", 500.0, 3.0, False, False)]),
    ):
        write_msls_side(miami / side, rows)
        (miami / side / "raw.csv").unlink()
    return root


def make_images(root: Path, n: int = 10) -> list[Path]:
    """Half-bright, half-dark images at a size other than LABEL_SIZE (so labelling must resize)."""
    root.mkdir(parents=True)
    paths = []
    for i in range(n):
        img = np.zeros((32, 40, 3), np.uint8)
        img[:, : 4 * (i + 1)] = 255
        paths.append(root / f"@{i:03d}@img@.png")
        Image.fromarray(img).save(paths[-1])
    return paths


def labels_key(paths: list[Path], root: Path) -> dict:
    """The labels key pseudo_labels builds on a CPU in the running precision (kept in sync by
    test_interrupted_run_resumes_with_the_rest)."""
    from semvpr.core.precision import compute_key
    from semvpr.segmentation.pseudolabels import VERSION, image_list_identity

    return {
        "version": VERSION,
        "teacher": "teacher-abc",
        "images": image_list_identity(paths, root),
        "image_size": list(LABEL_SIZE),
        **compute_key("cpu"),
    }


# ---------------------------------------------------------------- real-street fixtures: frames, segmenter dirs

#: Tiny frame-aligned sets: the eval size the frames are written at (no resize on reading).
FRAME_SIZE = (64, 96)


def write_frames(root: Path, traversals: dict[str, list[int]], name: str = "frame{:03d}.png") -> Path:
    """One folder per traversal under ``root``; ``traversals[t][i]`` is the seed of frame i's pixels, so two
    traversals show the same image where their seeds agree. Written at FRAME_SIZE."""
    for traversal, seeds in traversals.items():
        for i, seed in enumerate(seeds):
            path = root / traversal / name.format(i)
            path.parent.mkdir(parents=True, exist_ok=True)
            pixels = np.random.default_rng(seed).integers(0, 255, (*FRAME_SIZE, 3), dtype=np.uint8)
            Image.fromarray(pixels).save(path)
    return root


def frame_images(root: Path, traversal: str) -> torch.Tensor:
    """A traversal's frames as a (N,3,H,W) batch in [0, 1], in frame order (read with PIL, no resize)."""
    paths = sorted((root / traversal).iterdir())
    return (
        torch.stack([torch.from_numpy(np.array(Image.open(p).convert("RGB"))).permute(2, 0, 1) for p in paths]).float()
        / 255
    )


def mixed_student(backbone, images: torch.Tensor, width: int = 8):
    """An untrained student whose dynamic-class bias is set so that about half of the pixels of ``images``
    come out static: its binary mask keeps some locations and drops others (not all or nothing)."""
    from semvpr.data.classes import STATIC_NAMES, TRAIN_ID_NAMES
    from semvpr.models.student import StudentSpec, student_architecture

    torch.manual_seed(0)
    spec = StudentSpec(width=width)
    student = student_architecture(spec, backbone).eval()
    static = torch.tensor([n in STATIC_NAMES for n in TRAIN_ID_NAMES])
    with torch.no_grad():
        logits = student(backbone.forward_frozen(images)).float()
        margin = logits[:, static].logsumexp(1) - logits[:, ~static].logsumexp(1)
        student.head.bias[~static] += margin.median()
    return student, spec


def write_student_dir(folder: Path, backbone, images: torch.Tensor, domain: str = "real") -> Path:
    """A student directory as semvpr.segment saves one (mixed_student's weights), trained_on camvid."""
    from semvpr.core.provenance import TrainedOn
    from semvpr.models.student import save_student

    student, spec = mixed_student(backbone, images)
    return save_student(
        student, spec, "efficientnet_lite0", backbone.frozen_identity(), [32, 48], TrainedOn("camvid", domain), folder
    )


#: A Mask2Former small enough to build in a second (random-init Swin pixel-level backbone).
TINY_TEACHER_MODEL = {
    "backbone": "swin",
    "backbone_weights": "none",
    "embed_dim": 16,
    "depths": [1, 1, 1, 1],
    "num_heads": [1, 1, 2, 2],
    "window_size": 4,
    "hidden_dim": 32,
    "num_attention_heads": 2,
    "encoder_layers": 1,
    "decoder_layers": 2,
    "num_queries": 8,
    "train_num_points": 256,
}


def write_teacher_dir(folder: Path, image_size: tuple[int, int] = (32, 48)) -> Path:
    """A teacher directory as semvpr.segment saves one (an untrained tiny Mask2Former), trained_on camvid at
    ``image_size``."""
    from semvpr.core.provenance import TrainedOn
    from semvpr.models.teacher import TeacherSpec, embedded_teacher
    from semvpr.segment import save_teacher

    torch.manual_seed(0)
    teacher = embedded_teacher(TeacherSpec(image_size=image_size, model=TINY_TEACHER_MODEL)).eval()
    save_teacher(teacher, folder, list(image_size), TrainedOn("camvid", "real"))
    return folder


#: GSV-Cities fixture: csv name -> (city_id, [(place_id, images)]). London has a place with fewer than
#: 4 images; OSL's place ids repeat London's (another city, other places).
GSV_CITIES: dict[str, tuple[str, list[tuple[int, int]]]] = {
    "London": ("London", [(130, 4), (131, 5), (132, 6), (133, 4), (7, 2)]),
    "OSL": ("OSL", [(130, 4), (131, 4), (5, 5)]),
    "Boston": ("Boston", [(0, 5), (1, 4)]),
}


def gsv_row(city_id: str, place_id: int, k: int) -> dict[str, object]:
    """Image k of a fixture place: year/month/heading vary, lat has a csv form that Python prints shorter."""
    return {
        "place_id": place_id,
        "year": 2007 + k,
        "month": 1 + (k * 5) % 12,
        "northdeg": (place_id * 37 + k * 90) % 360,
        "city_id": city_id,
        "lat": f"{51.4861 + place_id * 1e-3:.7f}",  # e.g. 51.6161000 in the csv, 51.6161 in the name
        "lon": -0.0895151 - 0.001 * place_id,
        "panoid": f"p{place_id}-{k}_Xy{k}",
    }


def gsv_name(row: dict[str, object]) -> str:
    """The file name gsv-cities' dataloader builds from a row (city_id, zero-padded place id mod 10^5,
    year, month, heading, then lat and lon as Python prints the floats, panoid)."""
    return (
        f"{row['city_id']}_{int(row['place_id']) % 100000:07d}_{int(row['year']):04d}_{int(row['month']):02d}_"
        f"{int(row['northdeg']):03d}_{float(row['lat'])!r}_{float(row['lon'])!r}_{row['panoid']}.jpg"
    )


def write_gsv_cities(root: Path, cities: dict[str, tuple[str, list[tuple[int, int]]]] | None = None) -> Path:
    """The GSV-Cities layout: Dataframes/<City>.csv (place_id, year, month, northdeg, city_id, lat, lon, panoid)
    and Images/<city_id>/<name>.jpg, one small image per row; rows of a city in shuffled place order."""
    columns = ["place_id", "year", "month", "northdeg", "city_id", "lat", "lon", "panoid"]
    for index, (city, (city_id, places)) in enumerate((cities or GSV_CITIES).items()):
        rows = [gsv_row(city_id, pid, k) for pid, n in places for k in range(n)]
        rows = [rows[i] for i in np.random.default_rng(index).permutation(len(rows))]
        lines = [",".join(columns)] + [",".join(str(r[c]) for c in columns) for r in rows]
        (root / "Dataframes").mkdir(parents=True, exist_ok=True)
        (root / "Dataframes" / f"{city}.csv").write_text("\n".join(lines) + "\n")
        for i, row in enumerate(rows):
            write_image(root / "Images" / city_id / gsv_name(row), 1000 * index + i)
    return root


def espnetv2_state(widths: list[int], seed: int = 0) -> dict[str, torch.Tensor]:
    """A state dict in the layout of ESPNetv2's Cityscapes files (20 channels), every value drawn (convolutions
    of unit gain, BatchNorm statistics and scales near 1, PReLU slopes in [0, 0.3]) so that inference reads each of
    them and the logits carry the input's signal."""
    from semvpr.models.espnetv2 import ESPNetv2Segmentation

    g = torch.Generator().manual_seed(seed)
    model = ESPNetv2Segmentation(widths, 20)
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.Conv2d):
                module.weight.copy_(
                    torch.randn(module.weight.shape, generator=g) * (1.0 / module.weight[0].numel()) ** 0.5
                )
                if module.bias is not None:
                    module.bias.copy_(torch.randn(module.bias.shape, generator=g) * 0.1)
            elif isinstance(module, torch.nn.BatchNorm2d):
                n = module.num_features
                module.weight.copy_(torch.rand(n, generator=g) * 0.4 + 0.8)
                module.bias.copy_(torch.randn(n, generator=g) * 0.1)
                module.running_mean.copy_(torch.randn(n, generator=g) * 0.1)
                module.running_var.copy_(torch.rand(n, generator=g) * 1.0 + 0.5)
            elif isinstance(module, torch.nn.PReLU):
                module.weight.copy_(torch.rand(module.weight.shape, generator=g) * 0.3)
    return model.state_dict()


def write_espnetv2(path: Path, widths: tuple[int, ...] = (16, 32, 64, 128), seed: int = 0) -> Path:
    """A weight file in the layout of ESPNetv2's authors' Cityscapes releases (random weights), its classifier
    made decisive (rows of zero mean, scaled up): its labels change across an image, static and dynamic classes
    both, as a trained segmenter's do."""
    path.parent.mkdir(parents=True, exist_ok=True)
    state = espnetv2_state(list(widths), seed)
    head = state["bu_dec_l4.merge_layer.3.weight"]
    state["bu_dec_l4.merge_layer.3.weight"] = (head - head.mean(1, keepdim=True)) * 30
    state["bu_dec_l4.merge_layer.3.bias"].zero_()
    torch.save(state, path)
    return path

"""Hostile dataset lists and caches: nothing is written outside the run and cache directories."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from semvpr.core.errors import SemvprError
from semvpr.core.io import inside
from semvpr.data.images import Reading
from semvpr.data.places import PlaceSet, read_dbstruct_mat, read_msls
from semvpr.segmentation.pseudolabels import pseudo_labels
from tests.helpers import (
    LABEL_SIZE,
    CountingTeacher,
    labels_key,
    make_images,
    write_dbstruct,
    write_jpg,
    write_msls_cities,
    write_msls_side,
)


def files_under(folder: Path) -> set[Path]:
    """Every file and link below ``folder`` (links not followed)."""
    return {Path(d) / n for d, dirs, files in os.walk(folder) for n in files + dirs}


def test_msls_key_climbing_out_of_the_images_folder_is_refused(tmp_path: Path) -> None:
    root = write_msls_cities(tmp_path / "msls")
    write_msls_side(root / "train_val" / "sf" / "query", [("../../../../../victim", 5.0, 6.0, False, True)])
    with pytest.raises(SemvprError, match=r"postprocessed\.csv: image name '\.\./.*victim\.jpg' leaves"):
        read_msls(root, "val")


@pytest.mark.parametrize("bad", ["../../victim.jpg", "/etc/victim.jpg", "000/../../victim.jpg"])
def test_dbstruct_names_leaving_the_image_root_are_refused(tmp_path: Path, bad: str) -> None:
    root = tmp_path / "pitts"
    write_jpg(root / "000" / "a.jpg")
    write_jpg(root / "queries_real" / "000" / "q.jpg")
    utm = np.zeros((2, 2))
    write_dbstruct(tmp_path / "p.mat", ["000/a.jpg", bad], utm, ["000/q.jpg"], utm[:1])
    with pytest.raises(SemvprError, match=r"p\.mat: image name .*victim\.jpg.* leaves"):
        read_dbstruct_mat(tmp_path / "p.mat", root)


def test_a_place_set_refuses_an_image_key_that_climbs_out(tmp_path: Path) -> None:
    root = tmp_path / "data"
    with pytest.raises(SemvprError, match="climbs out of the dataset root"):
        PlaceSet(
            "x",
            (root / "a.jpg", root / "b" / ".." / ".." / "victim.jpg"),
            (root / "q.jpg",),
            np.zeros((2, 2)),
            np.zeros((1, 2)),
            root=root,
        )
    # An image outside a given root is refused too (it used to widen the root to the images' common
    # folder without a word); without a root, the images' common folder is the root.
    with pytest.raises(SemvprError, match=r"q\.jpg is not under the dataset root"):
        PlaceSet("x", (root / "a.jpg",), (tmp_path / "q" / "q.jpg",), np.zeros((1, 2)), np.zeros((1, 2)), root=root)
    ok = PlaceSet("x", (root / "a.jpg",), (tmp_path / "q" / "q.jpg",), np.zeros((1, 2)), np.zeros((1, 2)))
    assert ok.root == tmp_path and ok.relative(ok.q_paths[0]) == "q/q.jpg"


def test_pseudo_labels_never_land_outside_the_cache(tmp_path: Path) -> None:
    """A textual '..' in an image path used to carry its label out of the labels directory."""
    Image.fromarray(np.zeros((32, 40, 3), np.uint8)).save(tmp_path / "victim.png")
    root = tmp_path / "deep" / "data"
    root.mkdir(parents=True)
    before = files_under(tmp_path)
    climbing = root / "a" / ".." / ".." / ".." / "victim.png"
    with pytest.raises(SemvprError, match="would leave"):
        pseudo_labels(
            CountingTeacher(teacher_key="t"), [climbing], Reading(LABEL_SIZE, 16, 0), tmp_path / "cache", root
        )
    assert {p for p in files_under(tmp_path) - before if not p.is_relative_to(tmp_path / "cache")} == set()


def test_inside_refuses_dotdot_absolute_and_symlinked_escapes(tmp_path: Path) -> None:
    base = tmp_path / "art"
    (base / "sub").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    os.symlink(tmp_path / "elsewhere", base / "link")
    assert inside(base, "sub/x.png") == base / "sub" / "x.png"
    for bad in ("../x.png", "sub/../../x.png", str(tmp_path / "x.png"), "link/x.png"):
        with pytest.raises(SemvprError, match="refusing to write"):
            inside(base, bad)


def test_a_planted_partial_link_in_a_shared_cache_is_refused(tmp_path: Path) -> None:
    """A '.labels-<hash>.partial' link made pseudo-labels land in the link's target."""
    from semvpr.core.cache import artifact_dir

    paths = make_images(tmp_path / "img")
    cache, victim = tmp_path / "cache", tmp_path / "victim"
    victim.mkdir()
    final = artifact_dir(cache, "labels", labels_key(paths, tmp_path / "img"))
    cache.mkdir()
    os.symlink(victim, final.parent / f".{final.name}.partial")
    with pytest.raises(SemvprError, match=r"\.partial is not a plain directory"):
        pseudo_labels(CountingTeacher(), paths, Reading(LABEL_SIZE, 16, 0), cache, tmp_path / "img")
    assert list(victim.iterdir()) == [] and not final.exists()


def test_links_planted_inside_a_partial_build_or_as_a_lock_are_not_followed(tmp_path: Path) -> None:
    from semvpr.core.cache import LOCK_DIR, artifact_dir, build_once

    cache, victim = tmp_path / "cache", tmp_path / "victim"
    victim.mkdir()
    final = artifact_dir(cache, "thing", {"a": 1})
    partial = final.parent / f".{final.name}.partial"
    partial.mkdir(parents=True)
    os.symlink(victim / "key.json", partial / "key.json")  # the key is written last, into the partial dir
    out = build_once(cache, "thing", {"a": 1}, lambda tmp: (tmp / "x").write_text("1"), resumable=True)
    assert (out / "key.json").is_file() and not (out / "key.json").is_symlink()
    (cache / LOCK_DIR).mkdir(exist_ok=True)
    lock = artifact_dir(cache, "other", {"b": 2})
    os.symlink(victim / "created-by-lock", cache / LOCK_DIR / f"{lock.name}.lock")
    with pytest.raises(SemvprError, match=r"lock file .* a link there is never followed"):
        build_once(cache, "other", {"b": 2}, lambda tmp: None)
    assert list(victim.iterdir()) == []


def test_orphaned_temp_dirs_of_dead_processes_are_reclaimed(tmp_path: Path) -> None:
    """kill -9 during a build left .<name>.tmp-* directories forever (and filled the disk)."""
    import socket
    import subprocess
    import sys

    from semvpr.core.cache import build_once
    from semvpr.core.io import temp_prefix

    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()
    host = socket.gethostname().split(".")[0]
    cache = tmp_path / "cache"
    orphan = cache / f".synthcity-abc.{host}-{dead}.k3j2h1g0.tmp"
    (orphan / "images").mkdir(parents=True)
    (orphan / "images" / "a.jpg").write_bytes(b"x" * 1000)
    ours = cache / f"{temp_prefix('thing')}a1b2c3d4.tmp"  # a live writer's (this process)
    ours.mkdir()
    other_host = cache / f".x.otherhost-{dead}.a1b2c3d4.tmp"  # a shared file system: not ours to judge
    other_host.mkdir()
    build_once(cache, "thing", {"a": 1}, lambda tmp: None)
    assert not orphan.exists() and ours.is_dir() and other_host.is_dir()


def test_a_cache_that_does_not_fit_the_disk_is_one_line_before_writing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a nearly full disk the memory-mapped cache ended in a bus error (exit 135, no message)."""
    import shutil

    from semvpr.core import io

    usage = shutil._ntuple_diskusage(10 * 2**30, 10 * 2**30 - 2**20, 2**20)  # 1 MiB free
    monkeypatch.setattr(io.shutil, "disk_usage", lambda _: usage)
    with pytest.raises(SemvprError, match=r"the trunk cache needs 12\.5 MiB in .*, but only 1\.0 MiB are free"):
        io.open_array(tmp_path / "db.npy", np.uint16, (100, 64, 1024), "the trunk cache")
    assert not (tmp_path / "db.npy").exists()
    small = io.open_array(tmp_path / "q.npy", np.uint16, (4, 8), "the trunk cache")
    assert small.shape == (4, 8) and os.stat(tmp_path / "q.npy").st_blocks * 512 >= small.nbytes  # reserved


def test_a_second_process_in_a_run_directory_is_refused(tmp_path: Path) -> None:
    """Two live jobs given one hydra.run.dir (a job requeued beside the one still running, two runs started in
    one second under the old second-resolution default) overwrote each other's checkpoints and metrics.json;
    the second is now one line and writes nothing of its own there."""
    from semvpr.core.io import sole_writer
    from tests.bad_input import cli

    run = tmp_path / "run"
    run.mkdir()
    with sole_writer(run, "hydra.run.dir"):  # the job already running there
        with (
            pytest.raises(SemvprError, match=r"^another process is running a job in .*run: two jobs in one"),
            sole_writer(run, "hydra.run.dir"),
        ):
            pass
        proc = cli("semvpr.eval", "experiment=tiny", "ckpt=none", f"hydra.run.dir={run}", cwd=tmp_path, timeout=600)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.strip().splitlines()[-1] == (
            f"semvpr: error: another process is running a job in {run}: two jobs in one directory overwrite each "
            "other's files; give this one its own hydra.run.dir, or wait for the other to end"
        )
        assert not (run / "eval.json").exists() and not list(tmp_path.glob("outputs"))
    with sole_writer(run, "hydra.run.dir"):  # released with its holder
        pass


def test_a_sweep_job_is_one_folder_whatever_its_overrides_hold() -> None:
    """Hydra's override_dirname nested a job's folder at each '/' of a value (the SLURM command's
    data.root=/data/pitts30k gave .../data.root=/data/pitts30k,...); conf/train.yaml names it as one folder."""
    from hydra import compose, initialize_config_dir
    from hydra.core.hydra_config import HydraConfig

    from semvpr.config.command import MAX_DIRNAME_BYTES, one_dir_name
    from semvpr.core.io import CONF_DIR

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(
            config_name="train",
            overrides=["data=folder", "data.root=/data/pitts30k", "seed=1", "paths.cache_dir=/c"],
            return_hydra_config=True,
        )
    previous = HydraConfig.instance().cfg
    HydraConfig.instance().set_config(cfg)  # what ${hydra:...} reads
    try:
        assert cfg.hydra.sweep.subdir == "data.root=%2Fdata%2Fpitts30k,data=folder,seed=1"
    finally:
        HydraConfig.instance().cfg = previous
    assert one_dir_name("data.root=a%2Fb") != one_dir_name("data.root=a/b")  # '%' escaped too: no two jobs meet
    long_a, long_b = (f"data.root=/{'x' * 300}/{end},seed=1" for end in "ab")
    names = {one_dir_name(long_a), one_dir_name(long_b), one_dir_name("data.root=/é" + "é" * 200)}
    assert len(names) == 3 and all(len(n.encode()) <= MAX_DIRNAME_BYTES and "/" not in n for n in names)


def test_a_sweep_over_a_key_left_out_of_job_names_gives_each_job_its_folder(tmp_path: Path) -> None:
    """conf/train.yaml leaves paths.cache_dir, trainer.max_epochs and data.preset out of job folder names (set once
    for a sweep); a sweep over one of them put every job in one folder (the second refused as a second process
    there, or with hydra/launcher=basic overwriting the first). Each job fails its check at once here."""
    from semvpr.config.command import name_swept_keys
    from tests.bad_input import cli

    sweep = tmp_path / "sweep"
    argv = ["-m", "experiment=tiny", "trainer.max_epochs=1,2", "model.num_clusters=0", "hydra/launcher=basic"]
    proc = cli("semvpr.train", *argv, f"paths.cache_dir={tmp_path / 'c'}", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    jobs = sorted(p.parent.name for p in sweep.glob("*/metrics.json"))
    assert jobs == [f"experiment=tiny,model.num_clusters=0,trainer.max_epochs={n}" for n in (1, 2)], jobs
    # A key set once stays out of the names; a command line naming the excluded keys itself is kept as given.
    assert name_swept_keys(["-m", "trainer.max_epochs=4", "seed=0,1"], "train") == [
        "-m",
        "trainer.max_epochs=4",
        "seed=0,1",
    ]
    own = ["seed=0,1", "hydra.job.config.override_dirname.exclude_keys=[]", "-m"]
    assert name_swept_keys(own, "train") == own


def test_an_earlier_jobs_record_never_stands_beside_a_new_jobs_files(tmp_path: Path) -> None:
    """A job started in a directory that holds an earlier job's record (eval.json, metrics.json) removes it
    first: killed or failed, the new job leaves no record saying its directory is complete."""
    from tests.bad_input import cli

    run = tmp_path / "run"
    run.mkdir()
    (run / "eval.json").write_text('{"status": "ok", "test/R@1": 99.0}')
    proc = cli(
        "semvpr.eval",
        "experiment=tiny",
        "ckpt=none",
        "data=folder",
        f"data.root={tmp_path / 'nowhere'}",
        f"hydra.run.dir={run}",
        cwd=tmp_path,
        timeout=600,
    )
    assert proc.returncode == 2 and "nowhere" in proc.stderr.strip().splitlines()[-1], proc.stderr
    assert not (run / "eval.json").exists()

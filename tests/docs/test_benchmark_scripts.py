"""Every script in benchmarks/ runs, with small arguments, as a user would start it: a benchmark that
nothing runs rots unseen (speed.py's NetVLAD reference once did). Slow: each starts Python with torch,
several train on the tiny preset."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from PIL import Image

from tests.bad_input import stage_line
from tests.camvid_fixture import write_camvid
from tests.helpers import REPO, write_frames


def _occluder_fixture(tmp: Path) -> list[str]:
    """occluders.py's arguments on a tiny frame-aligned set and a tiny CamVid written into ``tmp``."""
    frames = write_frames(tmp / "frames", {"day": [0, 1, 2], "night": [3, 4, 5]})
    camvid = write_camvid(tmp / "camvid", sizes={"train": 1, "val": 1, "test": 4})
    return ["--data", "frames", "--root", str(frames), "--camvid", str(camvid), "--batch", "2"] + [
        "data.database=day",
        "data.queries=night",
        "data.image_size=[64,96]",
    ]


#: script -> (its small arguments given a scratch dir, a fragment of its last stdout line)
SCRIPTS: dict[str, tuple[Callable[[Path], list[str]], str]] = {
    "aggregator_cost.py": (lambda t: ["--batch", "2", "--repeats", "1"], ""),
    "cache_keys.py": (lambda t: ["--dir", str(t / "keys"), "--repeat", "2", "--limit", "50"], "ratio="),
    "calibrate_synthcity.py": (
        lambda t: (
            ["--preset", "tiny", "--init-images", "10", "--clusters", "4", "--threads", "1"]
            + ["--cache-dir", str(t / "cache"), "--json", str(t / "calibration.json")]
        ),
        "",
    ),
    "code_shape.py": (lambda t: [str(REPO / "semvpr" / "core")], "raise SemvprError sites"),
    "ddp.py": (lambda t: ["--db", "8", "--batch", "2", "--steps", "1", "--reps", "1"], "world=2"),
    "eval_memory.py": (
        lambda t: ["--sizes", "10", "20", "--image-size", "64", "80", "--batch", "2", "--workers", "0"],
        "growth_mb=",
    ),
    "gpu.py": (
        lambda t: ["--device", "cpu", "--quick", "--work", str(t / "gpu"), "--record", str(t / "gpu.json")],
        "gpu_check devices=cpu",
    ),
    "mask_cost.py": (lambda t: ["--batch", "1", "--repeats", "1"], "teacher_cut="),
    "occluders.py": (lambda t: _occluder_fixture(t), "ratio="),
    "quickstart.py": (lambda t: ["--override", "experiment=tiny"], "floor_s="),
    "kernel_time.py": (lambda t: ["--override", "experiment=tiny"], "equal_recalls=1"),
    "recipe_cost.py": (
        lambda t: (
            ["--cache-dir", str(t / "cache"), "--aggregators", "gem", "--override", "experiment=tiny"]
            + ["--override", "data.image_size=[64,80]"]
        ),
        "gsv·gem=",
    ),
    "record.py": (
        lambda t: [str(t / "record.json"), "--", "python", "-c", "print('step 91.0 ms'); print('a=1 b=2.5 c=x')"],
        "a=1 b=2.5",
    ),
    "released.py": (
        lambda t: ["--batch", "1", "--repeats", "1", "--only", "cosplace", "salad"],
        "salad.teacher_over_none=",
    ),
    "reproducibility.py": (lambda t: ["--filters", "attention", "--epochs", "2", "experiment=tiny"], "identical=3/3"),
    "scale.py": (
        lambda t: (
            ["--sizes", "10", "20", "--image-size", "64", "80", "--batch", "4", "--workers", "0"] + ["--clusters", "4"]
        ),
        "",
    ),
    "semantic.py": (
        lambda t: (
            ["--preset", "tiny", "--eval-images", "4", "--threads", "1", "--data-cache", str(t / "cache")]
            + ["teacher.train.epochs=1", "student.epochs=1"]
        ),
        "",
    ),
    "shared_cpu.py": (lambda t: ["--work", str(t / "work"), "--override", "experiment=tiny"], "ratio="),
    "speed.py": (lambda t: ["--batch", "1", "--agg-batch", "2", "--reps", "1"], "aggregate_speedup="),
    "sweep_cost.py": (lambda t: ["--before", "HEAD", "--after", "HEAD", "--override", "experiment=tiny"], "ratio="),
}


def test_every_benchmark_script_has_a_smoke_run() -> None:
    assert {p.name for p in (REPO / "benchmarks").glob("*.py")} == set(SCRIPTS)


@pytest.mark.slow
@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_benchmark_script_runs_with_small_arguments(tmp_path: Path, script: str) -> None:
    args, fragment = SCRIPTS[script]
    proc = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / script), *args(tmp_path)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=1200,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.returncode == 0, (proc.stdout[-2000:], proc.stderr[-3000:])
    last = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    assert fragment in last, last
    if script == "calibrate_synthcity.py":
        # --json holds the numbers the last line prints, with the command and the machine.
        record = json.loads((tmp_path / "calibration.json").read_text(encoding="utf-8"))
        gain = float(last.split("gain=")[1].split()[0])
        assert round(record["mean_over_dataset_seeds"]["gain"], 1) == gain, (record, last)
        assert record["command"].startswith("python benchmarks/calibrate_synthcity.py --preset tiny"), record
        assert record["machine"]["precision"] == "fp32" and record["runs"], record
    if script == "gpu.py":
        # Every step ran on the CPU and passed, the record complete with each step's result.
        record = json.loads((tmp_path / "gpu.json").read_text(encoding="utf-8"))
        assert record["status"] == "complete" and record["last"]["devices"] == "cpu", record
        steps = ["placement", "tiny_sweep", "trunk_pass", "precisions", "fp32_drift", "ddp", "determinism"]
        assert list(record["steps"]) == steps and {s["status"] for s in record["steps"].values()} == {"ok"}, record
        assert record["steps"]["placement"]["result"]["module_calls"] > 100, record
        assert 150 < record["steps"]["trunk_pass"]["result"]["conv_gflop_per_image"] < 190, record  # conv1_1-conv4_3
    if script == "record.py":
        # What the command printed, its last line's fields, the command as typed and the machine.
        record = json.loads((tmp_path / "record.json").read_text(encoding="utf-8"))
        assert record["output"] == ["step 91.0 ms", "a=1 b=2.5 c=x"], record
        assert record["last"] == {"a": 1.0, "b": 2.5, "c": "x"}, record
        assert record["command"].startswith("python -c "), record
        assert record["machine"]["cores"] >= 1 and record["machine"]["cpu"], record
    if script == "quickstart.py":
        # The sweep's processes did work, and no schedule beats its CPU time spread over the cores.
        fields = {k: float(v) for k, v in (item.split("=") for item in last.split())}
        assert fields["cpu_s"] > 0, last
        assert fields["floor_s"] == pytest.approx(fields["cpu_s"] / fields["cores"], abs=1), last
        assert fields["floor_s"] <= fields["sweep_s"] + 1, last


def test_record_writes_nothing_when_the_benchmark_fails(tmp_path: Path) -> None:
    out = tmp_path / "record.json"
    proc = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "record.py"), str(out), "--", "python", "-c", "raise SystemExit(3)"],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.returncode != 0 and not out.exists(), (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "failed (exit 3); nothing recorded" in lines[0], proc.stderr


SCRIPT_FILES = sorted([*(REPO / "benchmarks").glob("*.py"), *(REPO / "experiments").glob("*/*.py")])


@pytest.mark.parametrize("script", SCRIPT_FILES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_script_main_turns_a_user_error_into_one_line(script: Path) -> None:
    tree = ast.parse(script.read_text())
    mains = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "main"]
    assert len(mains) == 1, "a script's entry point is one main()"
    assert [ast.unparse(d) for d in mains[0].decorator_list] == ["exit_on_user_error"]


@pytest.mark.parametrize(
    ("script", "args", "fragment"),
    [
        (
            "experiments/camvid-semantic/paired_masks.py",
            ["{tmp}/a", "{tmp}/b", "--root", "{tmp}/camvid"],
            "CamVid root",
        ),
        (
            "experiments/camvid-semantic/paired_masks.py",
            ["{tmp}/a", "{tmp}/b", "--root", "{camvid}"],
            "student directory",
        ),
        ("experiments/real-streets/figure.py", ["{tmp}/out", "{tmp}/gardens", "--out-png", "{tmp}/f.png"], "not found"),
    ],
)
def test_a_script_given_a_missing_folder_says_so_in_one_line(
    tmp_path: Path, script: str, args: list[str], fragment: str
) -> None:
    camvid = tmp_path / "cv"  # a CamVid folder of one val frame, so the students are what is missing
    for part, mode in (("val", "RGB"), ("valannot", "L")):
        (camvid / part).mkdir(parents=True)
        Image.new(mode, (48, 36)).save(camvid / part / "f.png")
    (camvid / "val.txt").write_text("/SegNet/CamVid/val/f.png /SegNet/CamVid/valannot/f.png\n")
    proc = subprocess.run(
        [sys.executable, str(REPO / script), *(a.format(tmp=tmp_path, camvid=camvid) for a in args)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"},
    )
    lines = [ln for ln in proc.stderr.strip().splitlines() if not stage_line(ln)]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith("semvpr: error: ") and fragment in lines[0], lines[0]
    assert not (tmp_path / "f.png").exists()

"""experiments/published-masks/run.sh end to end on fixture files: a release file in its author's layout,
a place set, a teacher and a student directory."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
import torch

from semvpr.config.build import build_backbone
from tests.helpers import make_folder, tiny_config, write_student_dir, write_teacher_dir
from tests.test_released import cosplace_model, save_state

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "experiments" / "published-masks" / "run.sh"


@pytest.mark.slow
def test_run_sh_evaluates_a_release_with_each_mask(tmp_path: Path) -> None:
    save_state(cosplace_model(), tmp_path / "cosplace.pth")
    root = make_folder(tmp_path / "places")
    teacher = write_teacher_dir(tmp_path / "teacher")
    cfg = tiny_config(tmp_path / "cache")
    trunk = build_backbone(cfg.backbone, 0)
    student = write_student_dir(tmp_path / "student", trunk, torch.rand(4, 3, 32, 48))
    env = {**os.environ, "FOLDER": str(root), "EVAL_ARGS": "data.image_size=[32,48] threads=1 data.num_workers=0"}
    env["PYTHONPATH"] = str(REPO)
    out = tmp_path / "out"
    args = ["bash", str(SCRIPT), str(out), str(teacher), str(student), f"{tmp_path / 'cosplace.pth'}:cosplace"]
    done = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-2000:]
    table = (out / "results.md").read_text()
    assert "## cosplace.pth on folder" in table
    rows = [line for line in table.splitlines() if "measured:" in line or "failed:" in line]
    assert len(rows) == 3, table
    assert sum("cosplace (ResNet50, released) (gem, mask=none)" in r for r in rows) == 1
    assert sum("cosplace (ResNet50, released) (gem, mask=teacher from" in r for r in rows) == 1
    # The CamVid student decodes another trunk (EfficientNet-Lite0's): its row says so in one line.
    assert sum("failed:" in r and "frozen trunk" in r for r in rows) == 1, table

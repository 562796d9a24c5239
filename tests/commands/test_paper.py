"""experiment=paper cannot rot: the real config, a handful of 480x640 images in the Pitts layout, CPU."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from semvpr.eval import evaluate_checkpoint
from semvpr.train import run_job
from tests.helpers import config, write_pitts_mat

# Per split: database places along a line (m) and queries next to some of them.
LAYOUT = {"train": ([0, 5, 60, 120, 200], [1, 61]), "val": ([0, 60, 120], [1, 59]), "test": ([0, 60, 120], [2, 121])}


def make_pitts30k(root: Path) -> Path:
    """pitts30k_{train,val,test}.mat plus 480x640 JPEGs where pytorch-NetVlad expects them."""
    rng = np.random.default_rng(0)
    for split, (db_x, q_x) in LAYOUT.items():
        db = [f"{split}/{i:06d}_pitch1_yaw1.jpg" for i in range(len(db_x))]
        q = [f"{split}/{i:06d}_pitch1_yaw1.jpg" for i in range(len(q_x))]  # same stems as database images
        for name, folder in [(n, root) for n in db] + [(n, root / "queries_real") for n in q]:
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)).save(folder / name, quality=90)
        write_pitts_mat(
            root / "datasets" / f"pitts30k_{split}.mat",
            split,
            db,
            q,
            db_utm=[(585000.0 + x, 4477000.0) for x in db_x],
            q_utm=[(585000.0 + x, 4477000.0) for x in q_x],
        )
    return root


@pytest.mark.slow
def test_paper_experiment_dry_run(tmp_path: Path) -> None:
    root = make_pitts30k(tmp_path / "pitts30k")
    small = [
        "trainer=cpu",
        "backbone.weights=none",
        "model.pca_dim=2",
        "data.num_workers=0",
        f"paths.cache_dir={tmp_path / 'cache'}",
    ]
    cfg = config("experiment=paper", f"data.root={root}", "+trainer.fast_dev_run=true", *small)
    # The paper's protocol, as composed: VGG16 conv5 trainable, K=64, SGD 1e-4 halved every 5 epochs.
    assert list(cfg.data.image_size) == [480, 640] and cfg.model.num_clusters == 64 and cfg.trainer.max_epochs == 30
    assert cfg.backbone.train_from == "conv5" and cfg.recipe.optimizer._target_ == "torch.optim.SGD"
    assert (cfg.recipe.scheduler.step_size, cfg.recipe.queries_per_epoch, cfg.recipe.cache_refresh) == (5, None, 1000)
    metrics = run_job(cfg, tmp_path / "run")
    assert metrics["status"] == "ok" and metrics["aggregator_init"]["features"] == 5 * 100
    assert metrics["tuples_per_epoch"][0] >= 1  # one training step ran on a mined tuple
    result = evaluate_checkpoint(
        config("data=pitts30k", f"data.root={root}", f"+ckpt={metrics['checkpoint']}", *small[3:], config_name="eval")
    )
    assert (result["database"], result["queries"]) == (3, 2)
    assert result["test/R@1"] == pytest.approx(metrics["test/R@1"])

"""Data-parallel training (trainer=ddp) on CPU with gloo: the work is split and the numbers are the
single-process ones. Every multi-process run happens in a subprocess, under a timeout."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from semvpr.core.errors import SemvprError
from semvpr.retrieval import distributed, mining
from semvpr.train import run_job
from tests.helpers import REPO, tiny_config

WORKER = REPO / "tests" / "retrieval" / "ddp_worker.py"


@pytest.mark.parametrize("world", [1, 2, 3])
def test_rank_shares_recombine_and_keep_eval_batches_whole(world: int) -> None:
    for n in range(0, 12):
        shares = [list(range(n))[distributed.rank_slice(n, r, world)] for r in range(world)]
        assert sum(shares, []) == list(range(n))
        assert max(map(len, shares)) - min(map(len, shares)) <= 1
        for batch in (1, 3, 5):
            blocks = [distributed.batch_block(n, batch, r, world) for r in range(world)]
            assert [i for b in blocks for i in range(b.start, b.stop)] == list(range(n))
            assert all(b.start % batch == 0 or b.start == n for b in blocks)  # whole batches


@pytest.mark.parametrize("world", [1, 2, 3])
def test_per_rank_batches_recombine_to_the_single_process_batch(world: int, monkeypatch: pytest.MonkeyPatch) -> None:
    sys.path.insert(0, str(WORKER.parent))
    from ddp_worker import features

    train = features()
    rules = mining.Mining(batch_size=3, cache_refresh=7, num_negatives=3, negative_candidates=12, margin=0.5)
    desc = np.random.default_rng(0).normal(size=(len(train.db) + len(train.q), 16)).astype(np.float32)

    def describe(store, index):  # type: ignore[no-untyped-def]
        rows = desc[: len(train.db)] if store is train.db else desc[len(train.db) :]
        return rows if index is None else rows[index]

    broadcasts: list = []  # what rank 0 sends (its tuples and negative cache), replayed on the others

    def epoch_batches(rank: int, size: int) -> list:
        monkeypatch.setattr(mining, "world", lambda: (rank, size))
        replay = iter(list(broadcasts))
        monkeypatch.setattr(
            mining,
            "from_rank_zero",
            lambda obj: broadcasts.append(copy.deepcopy(obj)) or obj if rank == 0 else copy.deepcopy(next(replay)),
        )
        return list(mining.TrainingEpoch(train, rules, mining.MiningPool.of(train, rules), 0, describe))

    single = epoch_batches(0, 1)
    ranks = [epoch_batches(r, world) for r in range(world)]
    assert all(len(batches) == len(single) for batches in ranks)
    for i, whole in enumerate(single):
        parts = [batches[i] for batches in ranks]
        if whole is None:  # no tuple in the global batch: every rank skips the step
            assert all(part is None for part in parts)
            continue
        assert torch.equal(torch.cat([p["trunk"] for p in parts if "trunk" in p]), whole["trunk"])
        pairs = [int((p["tuples"][:, 2:] >= 0).sum()) if "tuples" in p else 0 for p in parts]
        assert sum(pairs) == int((whole["tuples"][:, 2:] >= 0).sum())
        # Each rank divides by global pairs / world: the ranks' losses average to the global mean.
        assert all(p["pairs"] * world == whole["pairs"] == sum(pairs) for p in parts)


def _worker(world: int, out: Path) -> dict:
    proc = subprocess.run(
        [sys.executable, str(WORKER), str(world), str(out)], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return torch.load(out, weights_only=False)


@pytest.fixture(scope="module")
def single_process(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _worker(1, tmp_path_factory.mktemp("ddp") / "single.pt")


@pytest.mark.parametrize("world", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_gloo_epoch_equals_the_single_process_one(world: int, single_process: dict, tmp_path: Path) -> None:
    ranks = _worker(world, tmp_path / "ranks.pt")
    # Sharded refresh, gathered: the single-process descriptors bit for bit (whole eval batches).
    assert np.array_equal(ranks["db_desc"], single_process["db_desc"])
    # Mining on rank 0, broadcast: the same tuples (as recombined batches) and negative cache.
    assert ranks["num_tuples"] == single_process["num_tuples"] > 0
    assert np.array_equal(ranks["neg_cache"], single_process["neg_cache"])
    assert len(ranks["batches"]) == len(single_process["batches"])
    assert all(torch.equal(a, b) for a, b in zip(ranks["batches"], single_process["batches"]))
    # The epoch exercised uneven pair counts and an empty slice in a non-empty global batch.
    assert any(len(set(p)) > 1 for p in ranks["pairs"])
    assert any(0 in p and sum(p) > 0 for p in ranks["pairs"])
    # DDP's averaged gradient of the per-rank losses is the single-process gradient.
    for got, expected in zip(ranks["grads"], single_process["grads"]):
        assert (got is None) == (expected is None)
        if expected is not None:
            torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-7)


def test_ddp_outside_the_command_line_is_refused(tmp_path: Path) -> None:
    cfg = tiny_config(tmp_path / "cache", "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2")
    with pytest.raises(SemvprError, match="python -m semvpr.train"):
        run_job(cfg, tmp_path / "run")
    assert not (tmp_path / "cache").exists()  # refused before anything was built


def _train(tmp_path: Path, *overrides: str, multirun: bool = False) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.train",
            *(["-m"] if multirun else []),
            "experiment=tiny",
            f"paths.cache_dir={tmp_path / 'cache'}",
            *overrides,
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


DDP = ("trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2")


@pytest.mark.slow
def test_two_job_ddp_sweep_writes_one_sweep_dir_with_two_ok_jobs_and_one_report(tmp_path: Path) -> None:
    # threads=1 in both runs: their frozen passes run at one thread count on any machine (fp32 convolutions
    # give other bits at another count), so the two trunk caches hold the same features.
    _train(tmp_path, "seed=0,1", *DDP, "threads=1", f"hydra.sweep.dir={tmp_path / 'sweep'}", multirun=True)
    assert not (tmp_path / "outputs").exists()  # no second sweep (or run) directory from another rank
    assert len(list((tmp_path / "sweep").glob("results.md"))) == 1
    jobs = sorted(p.parent for p in (tmp_path / "sweep").rglob("metrics.json"))
    assert len(jobs) == 2 and all(json.loads((j / "metrics.json").read_text())["status"] == "ok" for j in jobs)
    assert all(Path(json.loads((j / "metrics.json").read_text())["checkpoint"]).is_file() for j in jobs)
    # Against one process: the same recalls and weights within 1e-4 (measured: 3.3e-6 at most on tiny).
    _train(tmp_path, "seed=0", "threads=1", f"hydra.run.dir={tmp_path / 'single'}")
    single = json.loads((tmp_path / "single" / "metrics.json").read_text())
    ddp = json.loads(next(j for j in jobs if "seed=0" in j.name).joinpath("metrics.json").read_text())
    assert ddp["recalls"] == single["recalls"]
    assert ddp["distributed"] == {"world_size": 2, "backend": "gloo"} and ddp["device"] == "cpu"
    assert single["distributed"] == {"world_size": 1, "backend": None}
    weights = [torch.load(m["checkpoint"], weights_only=True)["state_dict"] for m in (ddp, single)]
    for key in weights[1]:
        torch.testing.assert_close(weights[0][key], weights[1][key], rtol=0, atol=1e-4)


@pytest.mark.reproducibility
@pytest.mark.slow
def test_ddp_resume_is_bit_identical_at_the_same_world_size(tmp_path: Path) -> None:
    _train(tmp_path, *DDP, "trainer.max_epochs=2", f"hydra.run.dir={tmp_path / 'whole'}")
    # A 2-epoch run killed after its first epoch: its record says 2 epochs, last.ckpt holds epoch 1.
    _train(tmp_path, *DDP, "trainer.max_epochs=1", f"hydra.run.dir={tmp_path / 'resumed'}")
    for name, old, new in (
        ("config.yaml", "max_epochs: 1\n", "max_epochs: 2\n"),
        ("overrides.yaml", "trainer.max_epochs=1\n", "trainer.max_epochs=2\n"),
        ("hydra.yaml", "trainer.max_epochs=1\n", "trainer.max_epochs=2\n"),
    ):
        record = tmp_path / "resumed" / ".hydra" / name
        assert old in record.read_text(), name
        record.write_text(record.read_text().replace(old, new))
    # The README's resume command: the run's own config, no other override (experiment=tiny would be one).
    proc = subprocess.run(
        [sys.executable, "-m", "semvpr.train", "ckpt_path=last", f"hydra.run.dir={tmp_path / 'resumed'}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = [json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("whole", "resumed")]
    assert runs[0]["recalls"] == runs[1]["recalls"] and runs[0]["best/val/R@1"] == runs[1]["best/val/R@1"]
    weights = [torch.load(m["checkpoint"], weights_only=True)["state_dict"] for m in runs]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


@pytest.mark.slow
def test_submitit_local_runs_one_task_per_device(tmp_path: Path) -> None:
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    launcher = ("hydra/launcher=submitit_local", "hydra.launcher.gpus_per_node=0", "hydra.launcher.timeout_min=30")
    _train(
        tmp_path,
        *launcher,
        "hydra.launcher.tasks_per_node=2",
        *DDP,
        f"hydra.sweep.dir={tmp_path / 'ok'}",
        multirun=True,
    )
    jobs = list((tmp_path / "ok").rglob("metrics.json"))
    assert len(jobs) == 1 and json.loads(jobs[0].read_text())["status"] == "ok"
    logs = "".join(p.read_text() for p in (tmp_path / "ok" / ".submitit").rglob("*_log.err"))
    assert "GLOBAL_RANK: 1, MEMBER: 2/2" in logs
    # One task for two devices: refused in one line, recorded as the job's failure.
    _train(
        tmp_path,
        *launcher,
        "hydra.launcher.tasks_per_node=1",
        *DDP,
        f"hydra.sweep.dir={tmp_path / 'one'}",
        multirun=True,
    )
    failed = json.loads(next((tmp_path / "one").rglob("metrics.json")).read_text())
    assert failed["status"] == "failed" and "tasks_per_node=2" in failed["error"]


def test_a_rank_that_exits_before_joining_ends_the_wait_at_once() -> None:
    """Rank 0 waits for the ranks it started in Python, watching them: one that dies (a bad command line,
    a crash reading its caches) is one line at once, not a 30-minute hang in the process group's rendezvous."""
    import socket
    import time

    from semvpr.retrieval.launch import await_ranks

    with socket.create_server(("127.0.0.1", 0)) as listener:
        child = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit(3)"])
        tic = time.monotonic()
        with pytest.raises(SemvprError, match=r"rank 1 of the DDP job exited \(code 3\) before joining it"):
            await_ranks(listener, [child], poll_s=0.1)
        assert time.monotonic() - tic < 30


def test_sigterm_stops_rank_0_while_it_waits_for_the_other_ranks(tmp_path: Path) -> None:
    import signal
    import time

    script = tmp_path / "wait.py"
    script.write_text(
        "import signal, socket, subprocess, sys\n"
        "from semvpr.retrieval.launch import await_ranks\n"
        "def stop(signum, frame):\n"
        "    raise SystemExit(143)\n"
        "signal.signal(signal.SIGTERM, stop)\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'])\n"
        "try:\n"
        "    with socket.create_server(('127.0.0.1', 0)) as listener:\n"
        "        print('waiting', flush=True)\n"
        "        await_ranks(listener, [child])\n"
        "finally:\n"
        "    child.kill()\n"
    )
    proc = subprocess.Popen(
        [sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=REPO, env={"PYTHONPATH": str(REPO)}
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "waiting"
    tic = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 143 and time.monotonic() - tic < 30


def _fake_rank_command(log: Path) -> str:
    """A rank that checks in as semvpr's ranks do, then logs when it was told to go (or why not)."""
    return (
        "import os, sys, time\n"
        "from semvpr.core.errors import SemvprError\n"
        "from semvpr.retrieval.launch import _check_in\n"
        f"log = open({str(log)!r}, 'a')\n"
        "try:\n"
        "    _check_in()\n"
        "    log.write(f'go {time.monotonic()}\\n')\n"
        "except SemvprError as error:\n"
        "    log.write(f'refused {error}\\n')\n"
        "    sys.exit(1)\n"
    )


def test_the_started_ranks_wait_for_rank_0s_work_before_fit_outside_the_rendezvous(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The ranks rank 0 starts check in at once and wait, in Python, until rank 0's own work before fit
    (initialisation, untrained evaluation) is done and it joins them: they never sit in the process
    group's rendezvous for it."""
    import time

    from semvpr.retrieval import launch

    log = tmp_path / "ranks.log"
    monkeypatch.setattr(launch, "_child_command", lambda o, r, rank: [sys.executable, "-c", _fake_rank_command(log)])
    monkeypatch.setenv("PYTHONPATH", str(REPO))
    for key in ("LOCAL_RANK", "SLURM_PROCID"):
        monkeypatch.delenv(key, raising=False)
    with launch.job_ranks(3, 1, [], tmp_path) as join:
        time.sleep(3)  # rank 0's work before fit; the others have long checked in
        assert not log.exists() or log.read_text() == ""
        ready = time.monotonic()
        join()
        join()  # a second join is a no-op
        deadline = time.monotonic() + 30
        while len(log.read_text().splitlines()) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
    went = [float(line.split()[1]) for line in log.read_text().splitlines()]
    assert len(went) == 2 and min(went) >= ready


def test_the_started_ranks_share_the_cores_as_their_job_does(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A rank that rank 0 starts runs alone as Hydra sees it; it counts the jobs its job runs beside."""
    from semvpr.retrieval import launch

    log = tmp_path / "ranks.log"
    code = (
        "from semvpr.config.plan import launcher_jobs\n"
        "from semvpr.retrieval.launch import _check_in\n"
        "_check_in()\n"
        f"open({str(log)!r}, 'a').write(f'{{launcher_jobs()}}\\n')\n"
    )
    monkeypatch.setattr(launch, "_child_command", lambda o, r, rank: [sys.executable, "-c", code])
    monkeypatch.setenv("PYTHONPATH", str(REPO))
    for key in ("LOCAL_RANK", "SLURM_PROCID"):
        monkeypatch.delenv(key, raising=False)
    with launch.job_ranks(3, 1, [], tmp_path, jobs_beside=2) as join:
        join()
    assert log.read_text().split() == ["2", "2"]


def test_a_started_rank_ends_with_one_line_when_rank_0_ends_before_training(tmp_path: Path) -> None:
    import socket

    log = tmp_path / "rank.log"
    with socket.create_server(("127.0.0.1", 0)) as listener:
        env = {"PYTHONPATH": str(REPO), "LOCAL_RANK": "1", "SEMVPR_DDP_CHECK_IN": str(listener.getsockname()[1])}
        child = subprocess.Popen([sys.executable, "-c", _fake_rank_command(log)], env=env)
        conn, _ = listener.accept()
        assert conn.recv(16) == b"1"
        conn.close()  # rank 0 ends (a crash in its initialisation) without telling the rank to go
        assert child.wait(timeout=30) == 1
    assert log.read_text().strip() == "refused rank 0 of the DDP job ended before training began; its output says why"


def test_a_started_rank_whose_rank_0_is_gone_ends_with_one_line(tmp_path: Path) -> None:
    import socket

    with socket.create_server(("127.0.0.1", 0)) as listener:
        port = listener.getsockname()[1]  # closed below: nothing listens there any more
    log = tmp_path / "rank.log"
    env = {"PYTHONPATH": str(REPO), "LOCAL_RANK": "1", "SEMVPR_DDP_CHECK_IN": str(port)}
    child = subprocess.run([sys.executable, "-c", _fake_rank_command(log)], env=env, timeout=600)
    assert child.returncode == 1
    assert log.read_text().strip() == "refused rank 0 of the DDP job ended before training began; its output says why"


def test_child_run_dirs_are_quoted_for_hydra() -> None:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from semvpr.retrieval.launch import hydra_quoted

    parser = OverridesParser.create()
    for run_dir in ['/tmp/ru"n', "/tmp/it's", "/tmp/a,b=c", "/tmp/back\\slash", "/tmp/end\\", "/tmp/x y\\'"]:
        assert parser.parse_override(f"hydra.run.dir={hydra_quoted(run_dir)}").value() == run_dir


@pytest.mark.slow
def test_a_ddp_run_dir_holding_a_quote_trains(tmp_path: Path) -> None:
    """Its rank 1 once failed to parse the run dir and rank 0 hung in the rendezvous, ignoring SIGTERM."""
    run = tmp_path / 'ru"n'
    _train(tmp_path, *DDP, f"hydra.run.dir='{run}'")
    assert json.loads((run / "metrics.json").read_text())["status"] == "ok"


@pytest.mark.parametrize("rank", [0, 1])
def test_under_ddp_only_rank_zero_decomposes_the_database_and_every_rank_takes_its_whitening(
    monkeypatch: pytest.MonkeyPatch, rank: int
) -> None:
    sys.path.insert(0, str(WORKER.parent))
    from ddp_worker import DIM, Trunk
    from ddp_worker import features as toy_features

    from semvpr.models.aggregators.gem import GeM
    from semvpr.models.whitening import PCAWhitening
    from semvpr.retrieval import retriever as retriever_module

    torch.manual_seed(0)
    model = retriever_module.Retriever(Trunk(), GeM(dim=DIM), whitening=PCAWhitening(DIM, 4), eval_batch_size=6)
    db = toy_features().db
    zero = PCAWhitening(DIM, 4).fit(model.describe_store(db, None))  # what rank 0 fits
    fits: list[int] = []
    real_fit = PCAWhitening.fit
    monkeypatch.setattr(PCAWhitening, "fit", lambda self, x: fits.append(1) or real_fit(self, x))
    monkeypatch.setattr(retriever_module, "world", lambda: (rank, 2))
    sent: list[dict] = []
    monkeypatch.setattr(
        retriever_module, "from_rank_zero", lambda obj: sent.append(obj) or (obj if rank == 0 else zero.state_dict())
    )
    model.fit_whitening(db)
    assert fits == ([1] if rank == 0 else []) and (sent[0] is None) == (rank != 0)
    assert bool(model.whitening_fitted)
    torch.testing.assert_close(model.whitening.projection, zero.projection)
    torch.testing.assert_close(model.whitening.mean, zero.mean)

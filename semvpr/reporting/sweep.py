"""A sweep directory read back as data: its jobs (what each recorded), the rows they form and the orderings
the report's tables and figures share. Nothing here writes; ``semvpr.reporting.sweep_report`` and
``semvpr.reporting.figures`` render it."""

from __future__ import annotations

import functools
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from semvpr.core.errors import SemvprError
from semvpr.core.io import CONF_DIR, existing_dir, read_json, read_yaml

LEARNED = "+learned"  # a mask run with mask.weights=learned is reported as "<mask>+learned"
NO_MASK = "none"  # the mask choice every other mask is paired against


@dataclass
class Job:
    """One run of the sweep as read back from its directory."""

    dir: Path
    name: str
    aggregator: str  # the aggregator choice, marked with its recipe unless that is the default (aggregator_label)
    mask: str  # the mask choice, with LEARNED appended for learned class weights
    backbone: str
    seed: int | None
    ok: bool
    error: str
    metrics: dict[str, Any]
    #: Dataset roots the run recorded (data.root, paths.cache_dir): the only places images are drawn from.
    roots: tuple[Path, ...] = ()
    #: The filter preset the run was asked for on its command line (``filter=unet``), if any.
    preset: str | None = None
    #: Its other command-line settings (``model.num_clusters=16``), as written: a sweep's jobs that differ in
    #: one are reported apart (:func:`load_sweep`).
    settings: dict[str, str] = field(default_factory=dict)

    @property
    def cell(self) -> str:
        """The table row this run belongs to (besides its backbone): aggregator · mask."""
        return cell_name(self.aggregator, self.mask)

    def recall(self, n: int) -> float:
        """Test Recall@n in percent (nan when the run did not record it)."""
        value = self.metrics.get(f"test/R@{n}")
        return float(value) if isinstance(value, (int, float)) else math.nan


def weights_kind(weights: Any) -> str:
    """What a backbone's ``weights`` setting names, as recorded: imagenet, none, or file (a path is
    never recorded)."""
    text = str(weights).lower() if weights is not None else "none"
    return text if text in ("imagenet", "none") else "file"


def backbone_label(name: str, kind: str | None) -> str:
    """A table's backbone: its name, marked when its weights are not ImageNet's (runs that differ only
    in backbone.weights must not share a row)."""
    marks = {"none": "random init", "file": "own weights"}
    return f"{name} ({marks[kind]})" if kind in marks else name


#: The recipe runs are recorded with when they name none, and the one a table leaves unmarked.
DEFAULT_RECIPE = "triplet"


def aggregator_label(name: str, recipe: str | None) -> str:
    """A table's aggregator: its name, marked with the recipe it trained with when that is not the default
    (runs that differ only in recipe must not share a row)."""
    return name if recipe in (None, DEFAULT_RECIPE) else f"{name} ({recipe})"


def cell_name(aggregator: str, mask: str) -> str:
    """Display key of an (aggregator, mask) pair."""
    return f"{aggregator} · {mask}"


_PRESET = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_\-]*$")


@functools.cache
def preset_choices(preset: str) -> tuple[str, str] | None:
    """The (aggregator, mask) a filter preset of the project selects (conf/filter/<preset>.yaml), or None
    for a name that is not one."""
    path = Path(CONF_DIR) / "filter" / f"{preset}.yaml"
    if not _PRESET.match(preset) or not path.is_file():
        return None
    chosen: dict[str, str] = {}
    for entry in read_yaml(path, "filter preset").get("defaults", []):
        if isinstance(entry, dict):
            for key, value in entry.items():  # "override /aggregator": "sral"
                chosen[str(key).split("/")[-1]] = str(value)
    if "aggregator" not in chosen or "mask" not in chosen:
        return None
    return chosen["aggregator"], chosen["mask"]


@dataclass
class Sweep:
    """All jobs of one sweep directory, with the orderings the tables and figures share.

    Runs are grouped by what they recorded (aggregator, mask, mask weighting, backbone), never by
    a name known here: the baseline aggregator and the upper-bound masks are flags in metrics.json.
    """

    dir: Path
    jobs: list[Job]
    #: The overrides of the jobs the sweep was given that never started (:func:`unstarted_jobs`).
    not_started: list[tuple[str, ...]] = field(default_factory=list)

    @property
    def unfinished(self) -> list[Job]:
        """The jobs that started and left no end record (stopped, killed or still running)."""
        return [j for j in self.jobs if not j.ok and j.error.startswith(UNFINISHED)]

    @property
    def complete(self) -> bool:
        """Whether every job the sweep was given ended, ok or failed."""
        return not self.not_started and not self.unfinished

    @property
    def backbones(self) -> list[str]:
        """Backbones in a stable (alphabetical) order, unknown ones last."""
        return sorted({j.backbone for j in self.jobs}, key=lambda b: (b == "?", b))

    @property
    def baseline(self) -> str | None:
        """The aggregator a run recorded as the baseline (conf/aggregator: baseline: true), if any ran."""
        names = sorted({j.aggregator for j in self.jobs if j.metrics.get("baseline_aggregator") is True})
        return names[0] if names else None

    @property
    def upper_bounds(self) -> frozenset[str]:
        """Masks recorded as upper bounds (ground truth: a ceiling to read against, not a competitor)."""
        return frozenset(j.mask.removesuffix(LEARNED) for j in self.jobs if j.metrics.get("mask_upper_bound") is True)

    @property
    def aggregators(self) -> list[str]:
        """The baseline aggregator first, then the others alphabetically, unknown last."""
        return sorted({j.aggregator for j in self.jobs}, key=lambda a: (a != self.baseline, a == "?", a))

    @property
    def masks(self) -> list[str]:
        """No mask first, upper bounds last, each mask's learned-weights variant right after it."""
        bounds = self.upper_bounds
        return sorted(
            {j.mask for j in self.jobs},
            key=lambda m: (
                m.removesuffix(LEARNED) != NO_MASK,
                m.removesuffix(LEARNED) in bounds,
                m == "?",
                m.removesuffix(LEARNED),
                m.endswith(LEARNED),
            ),
        )

    @property
    def cells(self) -> list[str]:
        """Rows in reading order: aggregators outer, masks inner."""
        present = {j.cell for j in self.jobs}
        return [c for a in self.aggregators for m in self.masks if (c := cell_name(a, m)) in present]

    def upper_bound(self, cell: str) -> bool:
        """Whether a row's (or a mask's) mask is an upper bound."""
        return cell.rpartition(" · ")[2].removesuffix(LEARNED) in self.upper_bounds

    def preset(self, cell: str) -> str | None:
        """The filter preset every run of a row was asked for, if they all were and it selects the row's
        aggregator and mask (``filter=unet aggregator=gem`` is not ``unet``)."""
        presets = {j.preset for j in self.jobs if j.cell == cell}
        if len(presets) != 1 or (preset := presets.pop()) is None:
            return None
        aggregator, _, mask = cell.partition(" · ")
        return preset if preset_choices(preset) == (aggregator, mask.removesuffix(LEARNED)) else None

    def label(self, cell: str) -> str:
        """Display name of a row: by its preset where the runs were asked for one (``unet (sral ·
        student)``), marked when its mask is an upper bound."""
        preset = self.preset(cell)
        bound = self.upper_bound(cell)
        if preset is not None:
            return f"{preset} ({cell}, upper bound)" if bound else f"{preset} ({cell})"
        return f"{cell} (upper bound)" if bound else cell

    def mask_label(self, mask: str) -> str:
        """Display name of a mask column: marked when it is an upper bound."""
        return f"{mask} (upper bound)" if self.upper_bound(mask) else mask

    def jobs_of(self, cell: str, backbone: str, needs: str | None = None) -> list[Job]:
        """Jobs of one row, ok runs first then by seed, optionally only those holding file `needs`."""
        jobs = [j for j in self.jobs if j.cell == cell and j.backbone == backbone]
        jobs = [j for j in jobs if needs is None or (j.dir / needs).is_file()]
        return sorted(jobs, key=lambda j: (not j.ok, j.seed if j.seed is not None else math.inf, j.name))

    def learned_weights(self) -> dict[tuple[str, str], list[dict[str, float]]]:
        """Per (backbone, row), the learned class weights of each ok run, in table order."""
        runs: dict[tuple[str, str], list[dict[str, float]]] = {}
        for job in self.jobs:
            weights = numeric_weights(job.metrics.get("class_weights")) if job.ok else None
            if weights is not None:
                runs.setdefault((job.backbone, job.cell), []).append(weights)
        return {c: runs[c] for c in sorted(runs, key=lambda c: (c[0], self.cells.index(c[1])))}

    def image_path(self, stored: str) -> Path | None:
        """Find an image path stored by a run (relative paths are relative to the run's launch dir);
        None unless it lies under a dataset root some job recorded (a sweep directory is data)."""
        path = Path(stored)
        # The launch dir is usually the project root, an ancestor of outputs/multiruns/<date>/<time>.
        candidates = (
            [path] if path.is_absolute() else [r / path for r in (Path.cwd(), self.dir, *self.dir.resolve().parents)]
        )
        roots = {root.resolve() for job in self.jobs for root in job.roots}
        for candidate in candidates:
            if candidate.is_file() and any(candidate.resolve().is_relative_to(root) for root in roots):
                return candidate
        return None


def numeric_weights(value: object) -> dict[str, float] | None:
    """A run's recorded class weights if they are a name -> finite number mapping, else None."""
    if not isinstance(value, dict) or not value:
        return None
    ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value.values())
    return {str(k): float(v) for k, v in value.items()} if ok else None


def _error_line(error: object) -> str:
    """The telling line of an error: a traceback ends with the exception, so take the last line."""
    lines = [ln.strip() for ln in str(error or "").splitlines() if ln.strip()]
    return lines[-1][:200] if lines else ""


FACT_KEYS = ("aggregator", "recipe", "mask", "backbone", "seed", "mask.weights", "filter")


def _yaml(path: Path) -> Any:
    """A .hydra file as plain YAML data (``core.io.read_yaml``: no aliases, bounded size; interpolations
    stay text, nothing is resolved); None when missing."""
    return read_yaml(path, "run record") if path.is_file() else None


def _select(node: Any, dotted: str) -> Any:
    for key in dotted.split("."):
        node = node.get(key) if isinstance(node, dict) else None
    return node


#: Command-line settings of a mask control (``retrieval.controls``), named in a row's label even when no job of
#: the sweep varies them.
CONTROL_SETTINGS = ("mask.control", "mask.apply")
#: Command-line settings that never make a run another (where it caches, how Hydra launches it).
NOT_SETTINGS = ("paths.cache_dir", "hydra")


def _hydra_facts(job_dir: Path) -> tuple[dict[str, str], tuple[Path, ...], dict[str, str]]:
    """aggregator / recipe / mask / backbone / seed / mask weighting of a job from its .hydra files (for jobs that
    died before metrics.json), read as plain YAML (nothing resolved), and the dataset roots it recorded.
    The composed choices are used, so a filter preset counts as the aggregator and mask it chose. Last, the
    job's other overrides (key -> value as written)."""
    # lowest priority: the dir name itself, Hydra's override_dirname "aggregator=gem,mask=student,seed=1"
    facts = {k: v for k, _, v in (item.partition("=") for item in job_dir.name.split(",")) if k in FACT_KEYS and v}
    hydra_dir = job_dir / ".hydra"
    roots: list[Path] = []
    settings: dict[str, str] = {}
    try:
        config, hydra_cfg = _yaml(hydra_dir / "config.yaml"), _yaml(hydra_dir / "hydra.yaml")
        # mask.weights is usually "${filter.weights}" (text here): the preset's value stands for it.
        for key, fact in (
            ("seed", "seed"),
            ("filter.weights", "mask.weights"),
            ("mask.weights", "mask.weights"),
            ("backbone.weights", "backbone.weights"),
        ):
            value = _select(config, key)
            if isinstance(value, (str, int, float)) and "${" not in str(value):
                facts[fact] = weights_kind(value) if fact == "backbone.weights" else str(value)
        choices = _select(hydra_cfg, "hydra.runtime.choices")
        for key in ("aggregator", "recipe", "mask", "backbone"):
            if isinstance(choices, dict) and isinstance(choices.get(key), str):
                facts[key] = choices[key]
        overrides = _yaml(hydra_dir / "overrides.yaml")
        for item in overrides if isinstance(overrides, list) else []:
            if not isinstance(item, str):
                continue
            key, _, value = item.lstrip("+~").partition("=")
            key = "mask.weights" if key == "filter.weights" else key
            if key in FACT_KEYS:
                facts[key] = value
            elif key != "backbone.weights" and not key.startswith(NOT_SETTINGS):
                settings[key] = value
        launch = Path(str(_select(hydra_cfg, "hydra.runtime.cwd") or Path.cwd()))
        for key in ("data.root", "paths.cache_dir"):
            value = _select(config, key)
            if isinstance(value, str) and value and "${" not in value:
                roots.append(launch / Path(value).expanduser())
    except Exception:  # noqa: BLE001 - a damaged .hydra dir only costs us labels and images, never the report
        pass
    return facts, tuple(roots), settings


_RECALL_KEY = re.compile(r"^(untrained/)?test/R@\d+(_pos)?$")


def out_of_range(metrics: dict[str, Any]) -> str | None:
    """Why an ok job's recorded numbers cannot be its row (a recall not a number in [0, 100], a wall time
    not finite and >= 0), or None: a job's file gets the checks the value would get where it is made."""
    for key, value in metrics.items():
        if _RECALL_KEY.match(key) and (
            not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 <= value <= 100
        ):
            return f"metrics.json's {key}={value!r} is not a recall in [0, 100]"
    wall = metrics.get("wall_time_s")
    if wall is not None and (not isinstance(wall, (int, float)) or isinstance(wall, bool) or not 0 <= wall < math.inf):
        return f"metrics.json's wall_time_s={wall!r} is not a finite time >= 0"
    return None


#: How a job that started and left no end record is described (stopped, killed, or still running).
UNFINISHED = "did not finish"


def read_job(job_dir: Path, sweep_dir: Path) -> Job:
    """Read one job directory; a missing or unreadable metrics.json makes a failed job."""
    rel = job_dir.relative_to(sweep_dir).as_posix()
    name = job_dir.name if rel == "." else rel
    metrics: dict[str, Any] = {}
    error = ""
    path = job_dir / "metrics.json"
    if not path.is_file():
        error = f"{UNFINISHED}: no metrics.json"
    else:
        try:
            loaded = read_json(path, "job metrics")
            metrics = loaded if isinstance(loaded, dict) else {}
            error = "" if metrics else "metrics.json is not a JSON object"
        except SemvprError as err:
            error = f"unreadable metrics.json ({err})"
    ok = not error and metrics.get("status") == "ok"
    if ok and (error := out_of_range(metrics) or "") != "":
        ok = False
    if not ok and not error:
        error = _error_line(metrics.get("error")) or f"status {metrics.get('status')!r}"
    facts, roots, settings = _hydra_facts(job_dir)
    seed = metrics.get("seed", facts.get("seed"))
    try:
        seed = int(seed) if seed is not None else None
    except ValueError:
        seed = None
    mask = str(metrics.get("mask") or facts.get("mask") or "?")
    if (metrics.get("weights") or facts.get("mask.weights")) == "learned":
        mask += LEARNED
    # The preset asked for on the command line (overrides.yaml, else the job dir's name); a run that
    # recorded another preset than that is not labelled by one.
    preset = facts.get("filter")
    if preset is not None and metrics.get("filter", preset) != preset:
        preset = None
    return Job(
        job_dir,
        name,
        aggregator_label(
            str(metrics.get("aggregator") or facts.get("aggregator") or "?"),
            metrics.get("recipe") or facts.get("recipe"),
        ),
        mask,
        backbone_label(
            str(metrics.get("backbone") or facts.get("backbone") or "?"),
            metrics.get("backbone_weights") or facts.get("backbone.weights"),
        ),
        seed,
        ok,
        error,
        metrics,
        roots,
        preset,
        settings,
    )


#: semvpr's Hydra commands, as their jobs' records name them.
COMMANDS = ("train", "eval", "localize", "segment")
#: Each command whose sweeps have a table: the file its job writes as it ends, and the command that reads them.
TABLES = {"train": ("metrics.json", "python -m semvpr.report"), "eval": ("eval.json", "python -m semvpr.evaltable")}


def job_command(job_dir: Path) -> str | None:
    """The command whose job ``job_dir`` is: the one its Hydra record names (``hydra.job.name``: train, eval,
    localize, segment), else the one whose end record it holds (``TABLES``); None where neither says."""
    try:
        name = _select(_yaml(job_dir / ".hydra" / "hydra.yaml"), "hydra.job.name")
    except SemvprError:  # a damaged record: read_job says so in the job's row
        name = None
    if isinstance(name, str):
        return name
    return next((command for command, (record, _) in TABLES.items() if (job_dir / record).is_file()), None)


def job_dirs(sweep_dir: Path, command: str, finished_only: bool = False) -> set[Path]:
    """``command``'s jobs under ``sweep_dir``: the dirs holding its end record (``TABLES``) and, unless
    ``finished_only``, those with a Hydra record (a failed or killed job), but never another of semvpr's commands'
    jobs (an eval job beside training runs is no failed training run). A folder holding only such jobs is one
    line naming the command whose table reads them."""
    record = TABLES[command][0]
    dirs = {p.parent for p in sweep_dir.rglob(record)}
    if not finished_only:
        dirs |= {p.parent for p in sweep_dir.rglob(".hydra") if p.is_dir()}
    named = {d: job_command(d) for d in dirs}
    others = {d for d, name in named.items() if name in COMMANDS and name != command}
    foreign = sorted({named[d] for d in others})
    if others and others == dirs:
        tables = [f"`{TABLES[name][1]} {sweep_dir}`" for name in foreign if name in TABLES]
        raise SemvprError(
            f"{sweep_dir} holds {' and '.join(f'semvpr.{name}' for name in foreign)} jobs, not semvpr.{command}'s"
            + (f"; their table: {', '.join(tables)}" if tables else "")
        )
    return dirs - others


#: The file a sweep's launch writes into its sweep dir before its first job starts (``config.runs.record_plan``):
#: every job's overrides.
JOBS_FILE = "jobs.json"


def planned_jobs(sweep_dir: Path) -> list[tuple[str, ...]] | None:
    """The overrides of every job the sweep's latest launch was given (:data:`JOBS_FILE`), each as its
    ``.hydra/overrides.yaml`` lists them; None where that is not known (no such file: another sweeper, or a
    sweep from before it was written)."""
    path = sweep_dir / JOBS_FILE
    if not path.is_file():
        return None
    data = read_json(path, "sweep's job list")
    jobs = data.get("jobs") if isinstance(data, dict) else None
    if not isinstance(jobs, list) or not all(isinstance(j, list) and all(isinstance(o, str) for o in j) for j in jobs):
        raise SemvprError(f"{path} is not a sweep's job list (jobs: lists of overrides)")
    return [tuple(job) for job in jobs]


def unstarted_jobs(sweep_dir: Path, dirs: set[Path]) -> list[tuple[str, ...]]:
    """The planned jobs (:func:`planned_jobs`) that no folder among ``dirs`` ran: none has their overrides."""
    planned = planned_jobs(sweep_dir)
    if planned is None:
        return []
    started = set()
    for job_dir in dirs:
        try:
            overrides = _yaml(job_dir / ".hydra" / "overrides.yaml")
        except SemvprError:
            continue
        if isinstance(overrides, list):
            started.add(tuple(str(o) for o in overrides))
    return [job for job in planned if job not in started]


def load_sweep(sweep_dir: str | Path, finished_only: bool = False) -> Sweep:
    """Discover the training job dirs (:func:`job_dirs`: metrics.json or a .hydra dir; ``finished_only``:
    metrics.json) and read them; unless ``finished_only``, the jobs the sweep was given that never started too."""
    sweep_dir = existing_dir(sweep_dir, "sweep dir", "pass the multirun dir, e.g. outputs/multiruns/<date>/<time>")
    dirs = job_dirs(sweep_dir, "train", finished_only)
    if not dirs:
        raise SemvprError(
            f"no job dirs in {sweep_dir} (none holds metrics.json or .hydra/); "
            "pass the multirun dir written by `python -m semvpr.train -m ...`"
        )
    jobs = [read_job(d, sweep_dir) for d in sorted(dirs)]
    not_started = [] if finished_only else unstarted_jobs(sweep_dir, dirs)
    # Jobs that differ in a setting besides the seed and the labelled choices are other runs, not more seeds of
    # one: their backbone label names it, so they form rows (and gains) of their own.
    values: dict[str, set[str | None]] = {k: set() for j in jobs for k in j.settings}
    for job in jobs:
        for key, seen in values.items():
            seen.add(job.settings.get(key))
    # A mask control is named wherever a job sets one, varied or not: its numbers are not its mask's own.
    varied = sorted(k for k, seen in values.items() if len(seen) > 1 or k.startswith(CONTROL_SETTINGS))
    for job in jobs if varied else ():
        shown = ", ".join(f"{k}={job.settings.get(k, 'default')}" for k in varied)
        job.backbone = f"{job.backbone} ({shown})"
    return Sweep(sweep_dir, jobs, not_started)


def mean_std(values: list[float]) -> tuple[float, float]:
    """Mean and sample std (ddof=1) of the finite values; std is nan for fewer than two."""
    vals = np.array([v for v in values if math.isfinite(v)], dtype=np.float64)
    if vals.size == 0:
        return math.nan, math.nan
    return float(vals.mean()), float(vals.std(ddof=1)) if vals.size > 1 else math.nan


def sweep_dir_of(sweep_dir: str, launch_dir: str | None) -> Path:
    """A multirun's sweep dir: ``hydra.sweep.dir`` (``sweep_dir``) relative to the directory the sweep was
    launched from (``hydra.runtime.cwd``: ``launch_dir``; None: the working directory)."""
    path = Path(sweep_dir)
    return path if path.is_absolute() else Path(launch_dir or os.getcwd()) / path

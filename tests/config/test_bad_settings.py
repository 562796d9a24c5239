"""Bad command-line values of train, eval, localize and segment (types, ranges, unknown keys, ``_target_``,
patterns, the recipe's and the segmenters' settings): exit 2 and one line (tests/bad_input.py runs each row)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.bad_input import EVAL, LOCALIZE, TRAIN, Case, nordland, rows, run_case
from tests.helpers import make_folder


def _no_descriptors(cache: Path) -> None:
    """The bad value was refused before the descriptor pass."""
    assert not cache.is_dir() or not any(p.name.startswith("descriptors-") for p in cache.iterdir())


CASES: dict[str, Case] = {
    "num_clusters=abc": Case(TRAIN, lambda t, c: ["model.num_clusters=abc"], "model.num_clusters='abc'"),
    "seed=abc": Case(TRAIN, lambda t, c: ["seed=abc"], "seed='abc'"),
    "student.flip=maybe": Case(
        TRAIN, lambda t, c: ["student.flip=maybe"], "student.flip='maybe' must be true or false"
    ),
    "seed=-1": Case(TRAIN, lambda t, c: ["seed=-1"], "seed=-1"),
    "lr=-1": Case(TRAIN, lambda t, c: ["recipe.optimizer.lr=-1"], "recipe.optimizer.lr=-1"),
    "num_figure_queries=0": Case(TRAIN, lambda t, c: ["num_figure_queries=0"], "num_figure_queries=0"),
    "jobs_per_gpu=0": Case(TRAIN, lambda t, c: ["jobs_per_gpu=0"], "jobs_per_gpu=0 must be a whole number >= 1"),
    "check_loss_every_n_steps=0": Case(
        TRAIN, lambda t, c: ["check_loss_every_n_steps=0"], "check_loss_every_n_steps=0 must be a whole number >= 1"
    ),
    # null was let through and failed as a TypeError once training had ended
    "num_figure_queries=null": Case(TRAIN, lambda t, c: ["num_figure_queries=null"], "num_figure_queries=null must"),
    "precision=foo": Case(TRAIN, lambda t, c: ["trainer.precision=foo"], "trainer.precision='foo'"),
    "negative radius": Case(TRAIN, lambda t, c: ["recipe.positive_radius=-5"], "recipe.positive_radius=-5"),
    "model=netvlad": Case(TRAIN, lambda t, c: ["model=netvlad"], "model=netvlad is recipe=triplet"),
    "model.margin": Case(TRAIN, lambda t, c: ["model.margin=0.2"], "recipe.margin=0.2"),
    "eval model=netvlad": Case(EVAL, lambda t, c: [f"ckpt={c}", "model=netvlad"], "recipe=triplet"),
    "eval ckpt in a sweep job's folder, unquoted": Case(
        EVAL, lambda t, c: [f"ckpt={t}/filter=unet,seed=0/tested.ckpt"], "\"ckpt='"
    ),
    # A value the config leaves unset (???), named as the user sets it: Hydra's traceback for ckpt and queries;
    # a reader's own key (data.test.root=DIR) for data.root, which sets no other split.
    "eval without ckpt": Case(EVAL, lambda t, c: [], "error: ckpt is not set; pass it on the command line (ckpt=...)"),
    "localize without queries": Case(LOCALIZE, lambda t, c: [f"ckpt={c}"], "error: queries is not set"),
    "eval data=folder without data.root": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data=folder"], "error: data.root is not set"
    ),
    "eval data=frames without data.database": Case(
        EVAL,
        lambda t, c: [f"ckpt={c}", "data=frames", f"data.root={t}", "data.queries=b"],
        "error: data.database is not set",
    ),
    # A control of a checkpoint without a mask: refused before any pass.
    "eval mask.control=random without a mask": Case(
        EVAL,
        lambda t, c: [f"ckpt={c}", "mask.control=random"],
        "mask.control=random needs a mask to control; mask=none has none",
        cache_check=_no_descriptors,
    ),
    "localize top_k=0": Case(LOCALIZE, lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=0"], "top_k=0"),
    "localize top_k=-1": Case(LOCALIZE, lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=-1"], "top_k=-1"),
    "localize top_k=abc": Case(LOCALIZE, lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=abc"], "top_k='abc'"),
    "localize top_k=null": Case(LOCALIZE, lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=null"], "top_k=null must"),
    "gsv recipe.optimizer.lr": Case(
        TRAIN,
        lambda t, c: ["recipe=gsv", "recipe.optimizer.lr=0.1"],
        "override aggregator.gsv.optimizer.lr=0.1, or recipe.default.optimizer.lr=0.1",
    ),
    "gsv places_per_batch=1": Case(
        TRAIN, lambda t, c: ["recipe=gsv", "recipe.places_per_batch=1"], "places_per_batch=1"
    ),
    "gsv under ddp": Case(
        TRAIN,
        lambda t, c: ["recipe=gsv", "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"],
        "use trainer=cpu or trainer=gpu",
    ),
    # Model sizes past what any machine holds: one line, not the allocator's traceback (a TB-sized model).
    "num_clusters=1e12": Case(
        EVAL,
        lambda t, c: ["ckpt=none", "aggregator=netvlad", "model.num_clusters=1000000000000"],
        "model.num_clusters=1000000000000 must be a whole number from 2 to 2147483647",
    ),
    "num_clusters=2^31-1": Case(
        EVAL,
        lambda t, c: ["ckpt=none", "aggregator=netvlad", "model.num_clusters=2147483647"],
        "more than this machine could allocate; lower its sizes (aggregator.num_clusters=2147483647)",
    ),
    "mixvpr descriptor of 1e10": Case(
        TRAIN,
        lambda t, c: [
            "aggregator=mixvpr",
            "aggregator.out_channels=100000",
            "aggregator.out_rows=100000",
        ],
        "out of memory: a step asked for",
    ),
    "pca_dim wider than the descriptor": Case(
        TRAIN, lambda t, c: ["model.pca_dim=100000000"], "model.pca_dim=100000000: PCA reduces the aggregator's"
    ),
    # A path setting of another type than a name, empty, or null where the reader needs it.
    **{
        f"data.root={v}": Case(EVAL, lambda t, c, v=v: [f"ckpt={c}", "data=folder", f"data.root={v}"], line)
        for v, line in (
            ("null", "data.root=null, but semvpr.data.places.read_utm_folder needs its root: set data.root"),
            ("2024", "data.root=2024 is not a path; a folder or file of that name is quoted: data.root='2024'"),
            ("[a,b]", "data.root=['a', 'b'] is not a path: name one file or folder"),
            ("''", "data.root='' names no file or folder"),
        )
    },
    "data.test.split=null": Case(
        EVAL,
        lambda t, c: [f"ckpt={c}", "data=folder", f"data.root={t}", "data.test.split=null"],
        "data.test.split=null, but semvpr.data.places.read_utm_folder needs its split",
    ),
    "localize queries=null": Case(
        LOCALIZE, lambda t, c: [f"ckpt={c}", "queries=null"], "queries=null: name the folder"
    ),
    # Lightning would put fit on a GPU its "auto" finds while every other stage ran on the CPU.
    **{
        f"trainer.accelerator={v}": Case(
            TRAIN,
            lambda t, c, v=v: [f"trainer.accelerator={v}"],
            f"trainer.accelerator='{v}' is not one of ['cpu', 'gpu', 'cuda']",
        )
        for v in ("tpu", "auto", "CPU")
    },
    "traversals=-1": Case(TRAIN, lambda t, c: ["data.traversals=-1"], "data.traversals=-1"),
    "train data.test._target_=builtins.print": Case(
        TRAIN, lambda t, c: ["data.test._target_=builtins.print"], "the key _target_ is refused"
    ),
    "eval a mapping value holding _target_": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "+data.extra={_target_:os.getcwd}"], "the key _target_ is refused"
    ),
    "segment model._partial_": Case(
        ["semvpr.segment"], lambda t, c: [f"seg.root={t}", "teacher.model._partial_=true"], "the key _partial_"
    ),
    # Settings segment reads only after its segmenters have trained: refused before.
    **{
        f"segment {arg}": Case(["semvpr.segment"], lambda t, c, arg=arg: [f"seg.root={t}", arg], line)
        for arg, line in (
            ("num_figure_images=0", "num_figure_images=0 must be a whole number >= 1"),
            ("eval_batch_size=0", "eval_batch_size=0 must be a whole number from 1"),
            ("score_test=maybe", "score_test='maybe' must be true or false"),
            ("seg.num_workers=-1", "seg.num_workers=-1 must be a whole number >= 0"),
            ("student.train.epochs=3", "student.train.epochs is not a setting of the project's config"),
            # The segmenters' counts and rates: an untrained teacher saved as trained, or torch's traceback.
            ("teacher.train.epochs=0", "teacher.train.epochs=0 must be a whole number >= 1"),
            ("student.lr=-1", "student.lr=-1 must be a finite number > 0"),
        )
    },
    "frame_pattern alternation in a repeat": Case(
        EVAL,
        lambda t, c: nordland(t, c, "data.frame_pattern='(x|xx)*(\\d+)\\.jpg'", frame="x" * 40),
        "repeats a repeat or an alternation",
        timeout=600,
    ),
    "frame_pattern nested repeat": Case(
        EVAL,
        lambda t, c: nordland(t, c, "data.frame_pattern='(?:y+)+z?(\\d+)\\.jpg'", frame="y" * 40),
        "repeats a repeat or an alternation",
        timeout=600,
    ),
    "frame_pattern backreference": Case(
        EVAL, lambda t, c: nordland(t, c, "data.frame_pattern='(\\d)\\1(\\d*)\\.jpg'"), "backreference"
    ),
    "frame_pattern four unbounded repeats": Case(
        EVAL,
        lambda t, c: nordland(t, c, "data.frame_pattern='.*_.*_.*_(\\d+)\\.jpg'"),
        "at most three unbounded repeats",
    ),
    "frame_window 1e20": Case(
        EVAL, lambda t, c: nordland(t, c, "data.frame_window=100000000000000000000"), "data.frame_window="
    ),
    "frame_window int64 max": Case(
        EVAL, lambda t, c: nordland(t, c, f"data.frame_window={2**63 - 1}"), f"data.frame_window={2**63 - 1}"
    ),
    "recipe.margin=nan": Case(TRAIN, lambda t, c: ["recipe.margin=nan"], "recipe.margin=nan"),
    "recipe.loss.epsilon=nan": Case(
        TRAIN, lambda t, c: ["recipe=gsv", "recipe.loss.epsilon=nan"], "recipe.loss.epsilon=nan is not a finite"
    ),
    "recipe.loss.beta=-inf": Case(
        TRAIN, lambda t, c: ["recipe=gsv", "recipe.loss.beta=-inf"], "recipe.loss.beta=-inf is not a finite"
    ),
    "gsv loss without a gradient": Case(
        TRAIN,
        lambda t, c: ["recipe=gsv", "recipe.loss.epsilon=-5", "trainer.max_epochs=1", "threads=1"],
        "the loss gave no parameter a gradient in any of",
    ),
    "teacher.model.num_queries=1e9": Case(
        TRAIN, lambda t, c: ["teacher.model.num_queries=1e9"], "teacher.model.num_queries=1000000000.0"
    ),
    "teacher.model.hidden_dim past the bound": Case(
        TRAIN, lambda t, c: ["teacher.model.hidden_dim=200000"], "teacher.model.hidden_dim=200000"
    ),
    "student.static_classes=[]": Case(
        TRAIN, lambda t, c: ["student.static_classes=[]"], "student.static_classes=[]: expected a non-empty"
    ),
    "eval data.image_size past the bound": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data.image_size=[48,20000]"], "data.image_size[1]=20000"
    ),
    "eval teacher.inference_size past the bound": Case(
        EVAL,
        lambda t, c: [f"ckpt={c}", "teacher.inference_size=[9000,9000]"],
        "teacher.inference_size[0]=9000 must be a whole number from 1 to 4096",
    ),
    "recipe.margin=-1": Case(TRAIN, lambda t, c: ["recipe.margin=-1"], "recipe.margin=-1"),
    "recipe.negative_candidates=0": Case(
        TRAIN, lambda t, c: ["recipe.negative_candidates=0"], "recipe.negative_candidates=0"
    ),
    "recipe.batch_size=nan": Case(TRAIN, lambda t, c: ["recipe.batch_size=nan"], "recipe.batch_size=nan"),
    "recipe.batch_size=abc": Case(TRAIN, lambda t, c: ["recipe.batch_size=abc"], "recipe.batch_size='abc'"),
    "trainer.max_epochs=-5": Case(TRAIN, lambda t, c: ["trainer.max_epochs=-5"], "trainer.max_epochs"),
    "trainer.max_epochs=abc": Case(TRAIN, lambda t, c: ["trainer.max_epochs=abc"], "trainer.max_epochs"),
    "model.pca_dim=-1": Case(TRAIN, lambda t, c: ["model.pca_dim=-1"], "model.pca_dim"),
    "trainer.devices=0": Case(TRAIN, lambda t, c: ["trainer.devices=0"], "trainer.devices"),
    "trainer.devices=2 without ddp": Case(TRAIN, lambda t, c: ["trainer.devices=2"], "needs trainer=ddp"),
    "unknown key +model.fooo": Case(TRAIN, lambda t, c: ["+model.fooo=1"], "model.fooo is not a setting"),
    "unknown key +fooo": Case(TRAIN, lambda t, c: ["+fooo=1"], "fooo is not a setting"),
    "unknown key model.fooo": Case(TRAIN, lambda t, c: ["model.fooo=1"], "model.fooo is not a setting"),
    "train data.eval_radius=0": Case(TRAIN, lambda t, c: ["data.eval_radius=0"], "data.eval_radius=0"),
    "eval data.image_size=[0,0]": Case(EVAL, lambda t, c: [f"ckpt={c}", "data.image_size=[0,0]"], "data.image_size"),
    "eval data.image_size=[-1,80]": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data.image_size=[-1,80]"], "data.image_size[0]"
    ),
    "eval data.image_size=null": Case(EVAL, lambda t, c: [f"ckpt={c}", "data.image_size=null"], "data.image_size"),
    "eval data.num_workers=-1": Case(EVAL, lambda t, c: [f"ckpt={c}", "data.num_workers=-1"], "data.num_workers=-1"),
    **{
        f"eval data.eval_radius={v}": Case(
            EVAL,
            lambda t, c, v=v: [
                f"ckpt={c}",
                "data=folder",
                f"data.root={make_folder(t / 'f', 2)}",
                f"data.eval_radius={v}",
            ],
            f"data.eval_radius={v}",
            cache_check=_no_descriptors,
        )
        for v in ("0", "-5", "nan")
    },
}


#: The rows that run by default (each starts a Python with torch): one per class; the whole table with -m slow.
FAST = {
    "eval data.eval_radius=0",
    "eval mask.control=random without a mask",
    "eval without ckpt",
    "eval data=frames without data.database",
    "seed=abc",
    "student.flip=maybe",
    "eval ckpt in a sweep job's folder, unquoted",
    "localize top_k=abc",
    "num_figure_queries=null",
    "gsv recipe.optimizer.lr",
    "train data.test._target_=builtins.print",
    "frame_pattern nested repeat",
    "gsv loss without a gradient",
    "teacher.model.num_queries=1e9",
    "unknown key +model.fooo",
    "num_clusters=2^31-1",
    "data.root=null",
    "segment score_test=maybe",
}


@pytest.mark.parametrize("where", ["first", "between", "last"])
def test_multirun_flag_between_overrides_names_the_order_that_runs(where: str) -> None:
    """Hydra's parser takes -m before or after the overrides; between them it said only "unrecognized arguments"."""
    from semvpr.config.checks import check_overrides
    from semvpr.core.errors import SemvprError

    argv = {"first": ["-m", "experiment=tiny", "seed=0,1"], "last": ["experiment=tiny", "seed=0,1", "-m"]}.get(
        where, ["experiment=tiny", "-m", "seed=0,1"]
    )
    if where != "between":
        check_overrides(argv, "train")
        return
    with pytest.raises(
        SemvprError, match=r"^-m goes before the overrides .*: python -m semvpr.train -m experiment=tiny seed=0,1$"
    ):
        check_overrides(argv, "train")


def test_an_unparsable_override_is_named_with_the_quoted_form_that_parses(tmp_path: Path) -> None:
    from semvpr.config.checks import check_overrides
    from semvpr.core.errors import SemvprError

    bad = f"ckpt={tmp_path}/filter=unet,seed=0/checkpoints/tested.ckpt"
    with pytest.raises(SemvprError) as err:
        check_overrides(["experiment=tiny", bad], "eval")
    message = str(err.value)
    assert f"cannot parse the override {bad!r}" in message and "\n" not in message
    suggested = message.rsplit(": ", 1)[1].strip('"')
    assert suggested == f"ckpt='{bad.partition('=')[2]}'"
    check_overrides(["experiment=tiny", suggested], "eval")  # parses and composes


@pytest.mark.parametrize("case", rows(CASES, FAST))
def test_a_bad_setting_is_one_line_and_exit_2(tmp_path: Path, checkpoint: Path, case: str) -> None:
    run_case(CASES[case], tmp_path, checkpoint)


@pytest.mark.parametrize(
    ("overrides", "line"),
    [
        # Relabelled runs: metrics.json and the checkpoint's record named a file that is not the one run
        # (aggregator.name=null recorded choices.aggregator='None'; mask.name=null was a TypeError).
        (["aggregator.name=gem"], r"^aggregator\.name=gem: .* choose another with aggregator=NAME \(boq, gem,"),
        (["mask.name=null"], r"^mask\.name=null: .* choose another with mask=NAME"),
        (["backbones.vgg16.name=x"], r"choose another with backbone@backbones\.vgg16=NAME \(dinov2_vitb14,"),
        # What the optimizer or scheduler refuses, before any work (were TypeErrors at the first step or epoch).
        (["recipe.optimizer.weight_decay=null"], r"^recipe\.optimizer \(torch\.optim\.Adam\) refuses its settings"),
        (["recipe.scheduler.step_size=0"], r"^recipe\.scheduler \(torch\.optim\.lr_scheduler\.StepLR\) refuses"),
        (["recipe.scheduler.gamma=null", "trainer.max_epochs=6"], r"^recipe\.scheduler .* refuses its settings"),
        # Without a reload every epoch trained on epoch 0's batches and mining, silently.
        (
            ["trainer.reload_dataloaders_every_n_epochs=0"],
            r"^trainer\.reload_dataloaders_every_n_epochs=0 must be 1 \(",
        ),
        (["backbone.weights=null"], r"^backbone\.weights=null: give imagenet, none"),  # was torch's TypeError
        # Lightning's TypeError once the Trainer was built, after the caches, teacher and student.
        (["trainer.log_every_n_steps=abc"], r"^trainer\.log_every_n_steps='abc' must be a whole number >= 1"),
        (["trainer.num_sanity_val_steps=1.5"], r"^trainer\.num_sanity_val_steps=1\.5 must be a whole number"),
        # The report's flags: any text read as true (a run reported as the upper bound).
        (["mask.upper_bound=abc"], r"^mask\.upper_bound='abc' must be true or false"),
        # The mask controls: unknown values, and a control the mask cannot take.
        (["mask=student", "mask.control=bogus"], r"^mask\.control='bogus' is not one of \['none', 'objects', 'sky',"),
        (["mask=student", "mask.apply=db"], r"^mask\.apply='db' is not one of \['both', 'database', 'queries'\]$"),
        (["mask=student", "mask.control_seed=-1"], r"^mask\.control_seed=-1 must be a whole number"),
        (["mask=student", "mask.control_seed=abc"], r"^mask\.control_seed='abc' must be a whole number"),
        (["mask.control=shuffled"], r"^mask\.control=shuffled needs a mask to control; mask=none has none"),
        (["mask.apply=queries"], r"^mask\.apply=queries needs a mask to apply; mask=none has none"),
        (["mask=oracle", "mask.weights=learned", "mask.control=sky"], r"^mask\.control=sky makes a binary mask"),
        (["mask=student", "mask.weights=learned", "mask.apply=database"], r"^mask\.apply=database in training"),
        # NetVLAD's alpha is set from each feature's two nearest centroids: an IndexError after the trunk pass.
        (["model.num_clusters=1"], r"^model\.num_clusters=1 must be a whole number from 2 .* two nearest"),
        (["model.num_clusters=1", "aggregator=sral"], r"^model\.num_clusters=1 must be a whole number from 2"),
        # A constructor value of the wrong kind: the class's ValueError once the trunk pass had run.
        (["aggregator=gem", "aggregator.p=abc"], r"^aggregator\.p='abc': aggregator=gem expects a number$"),
        (["aggregator=mixvpr", "aggregator.grid=abc"], r"^aggregator\.grid='abc': .* a list of whole numbers$"),
        (["aggregator=gem", "aggregator.fc_dim=0.5"], r"^aggregator\.fc_dim=0\.5: .* a whole number or null$"),
        # A recipe class's value of the wrong kind, taken and misread: StepLR decayed at epochs 5, 10 for a step
        # of 2.5; MultiStepLR counted a string's letters (never decaying); a gamma of [1] trained and left a
        # checkpoint that does not load; MultiSimilarity's ValueError came as Hydra's traceback.
        (
            ["recipe.scheduler.step_size=2.5"],
            r"^recipe\.scheduler\.step_size=2\.5: torch\.optim\.lr_scheduler\.StepLR "
            r"expects a whole number$",
        ),
        (
            ["recipe=gsv", "aggregator=gem", "aggregator.gsv.scheduler.milestones=abc"],
            r"^aggregator\.gsv\.scheduler\.milestones='abc': .*MultiStepLR expects a list of whole numbers$",
        ),
        (["recipe.scheduler.gamma=[1]"], r"^recipe\.scheduler\.gamma=\[1\]: .*StepLR expects a number$"),
        (["recipe.optimizer.weight_decay=abc"], r"^recipe\.optimizer\.weight_decay='abc': torch\.optim\.Adam expects"),
        (
            ["recipe=gsv", "recipe.loss.alpha=abc"],
            r"^recipe\.loss\.alpha='abc': semvpr\.retrieval\.losses\.MultiSimilarity expects a number$",
        ),
    ],
)
def test_a_value_the_run_would_misread_or_a_class_refuses_is_one_line_first(overrides: list[str], line: str) -> None:
    from semvpr.config.checks import check_config, check_overrides
    from semvpr.core.errors import SemvprError
    from tests.helpers import config

    with pytest.raises(SemvprError, match=line):
        check_overrides(overrides, "train")
        check_config(config(*overrides))


def test_every_recipe_and_aggregator_schedule_passes_the_optimization_check() -> None:
    from semvpr.config.checks import check_config
    from semvpr.config.components import options
    from tests.helpers import config

    for aggregator in options("aggregator"):
        for recipe in options("recipe"):
            check_config(config(f"aggregator={aggregator}", f"recipe={recipe}"))


def test_init_overrides_given_as_one_string_is_one_line() -> None:
    """The string was read letter by letter ("Error parsing override 'data.a'")."""
    from semvpr.config.checks import check_config
    from semvpr.core.errors import SemvprError
    from tests.helpers import config

    with pytest.raises(SemvprError, match=r"^init\.overrides='abc': must be a list: init\.overrides=\[\.\.\.\]$"):
        check_config(config("ckpt=none", "init.overrides=abc", config_name="eval"))
    check_config(config("ckpt=none", "init.overrides=['preset=tiny']", config_name="eval"))


def test_an_unset_value_is_named_where_the_user_sets_it() -> None:
    """The end of a chain of plain interpolations; a relative one, a resolver or a value is where it stops."""
    from semvpr.core.spec import unset

    raw = {
        "ckpt": "???",
        "data": {"root": "???", "test": {"root": "${data.root}", "again": "${data.test.root}", "up": "${..root}"}},
        "recipe": {"lr": "${oc.select:aggregator.lr,0.1}"},
    }
    for key, named in (
        ("ckpt", "ckpt"),
        ("data.test.root", "data.root"),
        ("data.test.again", "data.root"),
        ("data.test.up", "data.test.up"),
        ("recipe.lr", "recipe.lr"),
        ("nowhere.at_all", "nowhere.at_all"),
    ):
        assert str(unset(raw, key)) == f"{named} is not set; pass it on the command line ({named}=...)", key

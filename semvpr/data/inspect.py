"""`python -m semvpr.data.inspect <hydra overrides>`: summarise the test PlaceSet a config points at."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from semvpr.core.errors import SemvprError, exit_on_user_error, unwrap_user_error
from semvpr.core.spec import unset
from semvpr.data.places import PlaceSet

DEFAULT_CONFIG_DIR = Path(__file__).resolve().parents[2] / "conf"


def compose_place_set(config_dir: Path, config_name: str, overrides: list[str], node: str) -> PlaceSet:
    """Compose the config and instantiate `node` (default data.test) into a PlaceSet."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from hydra.utils import instantiate
    from omegaconf import OmegaConf
    from omegaconf.errors import InterpolationToMissingValueError, MissingMandatoryValue, OmegaConfBaseException

    if not (config_dir / f"{config_name}.yaml").is_file():
        raise SemvprError(f"config {config_dir / (config_name + '.yaml')} not found; pass --config-dir")
    cfg = None
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            cfg = compose(config_name=config_name, overrides=overrides)
        target = OmegaConf.select(cfg, node)
        if target is None:
            raise SemvprError(f"config {config_name} has no '{node}' node to instantiate")
        places = instantiate(target)
        if isinstance(places, PlaceSet):
            places = places.with_eval_radius(OmegaConf.select(cfg, "data.eval_radius"))
    except Exception as err:  # hydra wraps errors raised by the target; find ours
        user = unwrap_user_error(err)
        if user is not None:
            raise user from None
        if isinstance(err, (MissingMandatoryValue, InterpolationToMissingValueError)) and cfg is not None:
            raise unset(OmegaConf.to_container(cfg, resolve=False), str(err.full_key)) from None
        if isinstance(err, (HydraException, OmegaConfBaseException)):
            # Hydra messages are multi-line; the first line says what is wrong.
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise SemvprError(f"config error ({config_name}, overrides {overrides}): {first}") from None
        raise
    if not isinstance(places, PlaceSet):
        raise SemvprError(f"'{node}' instantiated to {type(places).__name__}, expected a PlaceSet")
    return places


def positive_stats(places: PlaceSet, radius: float | None = None) -> dict[str, float | int]:
    """The JSON summary: counts and positives (the set's own, or within `radius` m; mean over all queries)."""
    counts = np.array([len(p) for p in places.positives(radius)], dtype=np.int64)
    return {
        "database": len(places.db_paths),
        "queries": len(places.q_paths),
        "queries_with_positives": int((counts > 0).sum()),
        "mean_positives": round(float(counts.mean()) if len(counts) else 0.0, 2),
    }


def parser() -> argparse.ArgumentParser:
    """The command line of ``python -m semvpr.data.inspect``."""
    parser = argparse.ArgumentParser(prog="python -m semvpr.data.inspect", description=__doc__)
    parser.add_argument("overrides", nargs="*", help="hydra overrides, e.g. data=pitts30k data.root=DIR")
    parser.add_argument("--config-dir", type=Path, default=DEFAULT_CONFIG_DIR)
    parser.add_argument("--config-name", default="train")
    parser.add_argument("--node", default="data.test", help="config node that instantiates to a PlaceSet")
    parser.add_argument(
        "--radius",
        type=float,
        default=None,
        help="positive radius in metres (default: the set's evaluation ground truth)",
    )
    return parser


@exit_on_user_error
def main(argv: list[str] | None = None) -> None:
    """Print a human summary, then the JSON stats as the last line."""
    args = parser().parse_args(argv)
    places = compose_place_set(args.config_dir.expanduser().resolve(), args.config_name, args.overrides, args.node)
    stats = positive_stats(places, args.radius)
    print(places.summary())
    within = f"within {args.radius:g} m" if args.radius is not None else "among the evaluation positives"
    print(
        f"  queries with a database image {within}: "
        f"{stats['queries_with_positives']}/{stats['queries']} (mean {stats['mean_positives']} positives)"
    )
    print(json.dumps(stats))


if __name__ == "__main__":
    main()

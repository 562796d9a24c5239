"""The loaders of a fit's training batches: one per fit, its worker processes kept from pass to pass.

Each sub-epoch (recipe=triplet) and each epoch (recipe=gsv) draws new batches; a loader made for each pass
forks its workers anew every time. :class:`FitLoader` is made once: its batch sampler yields the batches of
the pass at hand, whose items name what to read (a mined tuple, an image's row), and its workers persist.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from semvpr.retrieval.distributed import world


def loader_settings(num_workers: int, streams: bool, device: torch.device | str) -> dict[str, Any]:
    """``num_workers`` and ``pin_memory`` of a loader over a feature store: on the CPU, workers only where the store
    streams images (cached features are a memory copy away: a worker would only add start-up); on a GPU,
    workers and pinned memory for cached stores too, so that the copies overlap the device's work. Under DDP the
    ``num_workers`` are the job's, divided among its ranks (at least one each where there are any)."""
    gpu = torch.device(device).type == "cuda"
    ranks = world()[1]
    share = max(1, num_workers // ranks) if num_workers else 0
    return {"num_workers": share if streams or gpu else 0, "pin_memory": gpu}


class PassBatches(Sampler[Sequence[Any]]):
    """The batches of the pass at hand (:meth:`FitLoader.over` sets them)."""

    def __init__(self) -> None:
        self.batches: Sequence[Sequence[Any]] = []

    def __len__(self) -> int:
        return len(self.batches)

    def __iter__(self) -> Iterator[Sequence[Any]]:
        return iter(self.batches)


class FitLoader:
    """One loader of ``dataset`` for a whole fit, passing over the batches :meth:`over` is given each time; where
    it has workers (:func:`loader_settings`), they persist across sub-epochs and epochs."""

    def __init__(
        self,
        dataset: Dataset,
        collate_fn: Callable[[list[Any]], Any],
        num_workers: int,
        streams: bool,
        device: torch.device | str,
    ) -> None:
        self.sampler = PassBatches()
        settings = loader_settings(num_workers, streams, device)
        self.loader = DataLoader(
            dataset,
            batch_sampler=self.sampler,
            collate_fn=collate_fn,
            persistent_workers=settings["num_workers"] > 0,
            **settings,
        )

    def over(self, batches: Sequence[Sequence[Any]]) -> DataLoader:
        """The loader, its next pass over ``batches`` (each a list of the dataset's keys)."""
        self.sampler.batches = batches
        return self.loader

"""Checks of weights read from a folder someone else wrote (a teacher's, a student's): what a tensor
holds is used as it is, so a damaged value is one line here, not a silent NaN mask later."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from semvpr.core.errors import SemvprError


def check_tensor(tensor: Tensor, name: str, source: Path) -> None:
    """A loaded weight: finite where it is a float; a BatchNorm variance >= 0."""
    if tensor.is_floating_point() and not torch.isfinite(tensor).all():
        raise SemvprError(f"{source}: {name!r} is not finite; the weights are damaged")
    if name.endswith("running_var") and bool((tensor < 0).any()):
        raise SemvprError(f"{source}: {name!r} has a negative variance; the weights are damaged")

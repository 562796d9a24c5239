"""User-facing errors: one exception type, printed as one line with exit code 2 by the CLIs."""

from __future__ import annotations

import functools
import re
import sys
from collections.abc import Callable
from typing import TypeVar

F = TypeVar("F", bound=Callable[..., object])


class SemvprError(Exception):
    """A problem with the user's input (data, weights, config), reported without a traceback."""


def exit_on_user_error(fn: F) -> F:
    """Wrap a CLI entry point so a SemvprError, or an OSError about a named file, prints one line on
    stderr and exits with code 2."""

    @functools.wraps(fn)
    def wrapper(*args: object, **kwargs: object) -> object:
        try:
            return fn(*args, **kwargs)
        except SemvprError as err:
            # Raised inside a Hydra task, SystemExit passes through Hydra's own error reporting,
            # which would print a traceback.
            print(f"semvpr: error: {one_line(err)}", file=sys.stderr)
            raise SystemExit(2) from None
        except OSError as err:
            # A file system refusal about a named path (permission, a read-only or full disk, a name
            # too long, a link loop) is the user's to fix: one line naming the file, not a traceback.
            if err.filename is None:
                raise
            print(f"semvpr: error: {err.filename}: {err.strerror or type(err).__name__}", file=sys.stderr)
            raise SystemExit(2) from None
        except RuntimeError as err:
            # Settings that need more memory than the machine has (a model's sizes, a batch): what was
            # asked for, in one line, not the allocator's traceback.
            asked = allocation_failure(err)
            if asked is None:
                raise
            print(
                f"semvpr: error: out of memory: a step {asked}; lower the batch or the model's sizes", file=sys.stderr
            )
            raise SystemExit(2) from None

    return wrapper  # type: ignore[return-value]


def one_line(err: BaseException) -> str:
    """The user-facing line of an error; one raised in a DataLoader worker arrives wrapped in its traceback."""
    lines = [line for line in str(err).splitlines() if line.strip()]
    return lines[-1].removeprefix(f"{SemvprError.__module__}.{SemvprError.__name__}: ") if lines else repr(err)


def unwrap_user_error(err: BaseException) -> SemvprError | None:
    """The SemvprError behind hydra's InstantiationException wrapping, if any."""
    seen: set[int] = set()
    cur: BaseException | None = err
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, SemvprError):
            return cur
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return None


def allocation_failure(err: BaseException) -> str | None:
    """What a failed allocation behind ``err`` asked for (torch's CPU allocator refusing, or a device out
    of memory) as a phrase ("asked for 417 GiB of memory, ..."); None when ``err`` is something else."""
    seen: set[int] = set()
    cause: BaseException | None = err
    while cause is not None and id(cause) not in seen:
        text = str(cause)
        names = {cls.__name__ for cls in type(cause).__mro__}
        if "OutOfMemoryError" in names or "can't allocate memory" in text:
            exact = re.search(r"allocate (\d+) bytes", text)
            shown = re.search(r"allocate ([\d.]+ [KMGTP]?i?B)", text)
            amount = f"{int(exact[1]) / 2**30:,.1f} GiB" if exact else shown[1] if shown else "more"
            return f"asked for {amount} of memory, more than this machine could allocate"
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return None

"""Regular expressions given by the user, matched with a bounded cost.

Python's ``re`` backtracks: ``(a+)+b`` over a name of 34 ``a`` s tries 2^34 ways before it fails. A
pattern from a setting is therefore parsed first and refused in one line unless its worst case is
bounded: no backreference or conditional (``\\1``, ``(?(1)...)``), no lookaround, no repeat or
alternation inside a repeat of varying count (``(a+)+``, ``(a|ab)*``), and at most
``MAX_SPLITS`` ways to divide a name among its repeats (the product of their widths, a repeat
without an upper bound counting ``MAX_NAME`` wide: three ``.*`` at most). It is matched against names
of at most ``MAX_NAME`` characters (a file name's limit), so one match costs at most about
``MAX_SPLITS`` steps (tens of milliseconds).
"""

from __future__ import annotations

import re
from typing import Any

try:  # Python >= 3.11
    from re import _constants as sre_constants  # type: ignore[attr-defined]
    from re import _parser as sre_parse  # type: ignore[attr-defined]
except ImportError:  # pragma: no cover - Python 3.10
    import sre_constants  # type: ignore[no-redef]
    import sre_parse  # type: ignore[no-redef]

from semvpr.core.errors import SemvprError

#: Longest name a pattern is matched against: a file name's limit on Linux (bytes; characters here).
MAX_NAME = 255
#: Most ways a pattern's repeats may divide a name among them (three unbounded repeats).
MAX_SPLITS = (MAX_NAME + 1) ** 3
#: Longest pattern read.
MAX_PATTERN = 1000

#: Repeats (a possessive one counted as any other: a bound, not an exact cost).
_REPEATS = {sre_constants.MAX_REPEAT, sre_constants.MIN_REPEAT, getattr(sre_constants, "POSSESSIVE_REPEAT", None)}
_ATOMIC = getattr(sre_constants, "ATOMIC_GROUP", None)
_REFUSED = {
    sre_constants.GROUPREF: "a backreference",
    sre_constants.GROUPREF_EXISTS: "a conditional group",
    sre_constants.ASSERT: "a lookaround",
    sre_constants.ASSERT_NOT: "a lookaround",
}

_NESTED = (
    "{key}={pattern!r} repeats a repeat or an alternation, as (a+)+ or (a|ab)* do: matching it can take time "
    "exponential in a name's length; write each repeat once"
)


def bounded_regex(pattern: Any, key: str) -> re.Pattern[str]:
    """``pattern`` compiled, or one line naming ``key`` where it is not a regular expression or its
    worst-case cost is not bounded (see the module docstring)."""
    if not isinstance(pattern, str):
        raise SemvprError(f"{key}={pattern!r}: expected a regular expression (text)")
    if len(pattern) > MAX_PATTERN:
        raise SemvprError(f"{key}: the pattern is {len(pattern)} characters long; the limit is {MAX_PATTERN}")
    try:
        compiled = re.compile(pattern)
        tree = sre_parse.parse(pattern)
    except (re.error, OverflowError, RecursionError) as err:
        raise SemvprError(f"{key}={pattern!r} is not a regular expression ({err})") from None
    splits = _splits(list(tree), pattern, key, inside_repeat=False)
    if splits > MAX_SPLITS:
        raise SemvprError(
            f"{key}={pattern!r}: its repeats can divide a name in more than {MAX_SPLITS:,} ways (at most three "
            "unbounded repeats such as .* or \\d+); use fewer, or bounded ones (\\d{1,6})"
        )
    return compiled


def match_name(regex: re.Pattern[str], name: str, key: str) -> re.Match[str] | None:
    """``regex.fullmatch(name)`` for a name of at most ``MAX_NAME`` characters (longer: one line)."""
    if len(name) > MAX_NAME:
        raise SemvprError(
            f"{name[:40]}...: the name is {len(name)} characters long; {key} matches names of up to {MAX_NAME}"
        )
    return regex.fullmatch(name)


def _splits(items: list[tuple[Any, Any]], pattern: str, key: str, *, inside_repeat: bool) -> int:
    """The number of ways the repeats of a parsed sequence can divide a name (product over the sequence,
    sum over alternatives); refuses what :func:`bounded_regex` refuses."""
    total = 1
    for op, arg in items:
        if op in _REFUSED:
            raise SemvprError(f"{key}={pattern!r} uses {_REFUSED[op]}, which a bounded pattern may not")
        if op in _REPEATS:
            low, high, body = arg
            if low > MAX_NAME:
                raise SemvprError(f"{key}={pattern!r}: a repeat of at least {low} matches no file name")
            width = min(high, MAX_NAME) - low + 1
            varies = width > 1
            if varies and inside_repeat:
                raise SemvprError(_NESTED.format(key=key, pattern=pattern))
            inner = _splits(list(body), pattern, key, inside_repeat=inside_repeat or varies)
            total *= width * inner if varies else inner ** max(low, 1)
        elif op == sre_constants.BRANCH:
            if inside_repeat:
                raise SemvprError(_NESTED.format(key=key, pattern=pattern))
            total *= sum(_splits(list(branch), pattern, key, inside_repeat=False) for branch in arg[1])
        elif op == sre_constants.SUBPATTERN:
            total *= _splits(list(arg[-1]), pattern, key, inside_repeat=inside_repeat)
        elif op == _ATOMIC:
            total *= _splits(list(arg), pattern, key, inside_repeat=inside_repeat)
        total = min(total, MAX_SPLITS + 1)  # enough to refuse; keeps the product small
    return total

"""The commands the docs show, read as a user copies them, and the one rule that makes each checkable.

Sources: every ``python -m semvpr…`` in README.md, docs/, the experiment and benchmark READMEs (code
blocks and inline code) and in the comments of conf/. A command is the text from ``python -m semvpr.<module>``
to the end of its line (``\\`` continues it) or code span; a ``# comment`` after it is not part of it.

The substitution rule (docs/commands.md says the same):

1. Syntax notes are not arguments: an optional part ``[ … ]`` is dropped, ``a|b`` takes ``a``, a token
   that is or ends in ``...`` (``data=...``, ``filter=a,b,...``) and the word ``[overrides]`` are dropped.
2. A placeholder (``<path>``, ``<run>/…``, an upper-case name such as ``DIR`` or ``GP_DIR``, ``/data/…``,
   ``/shared/…``) is a value the user supplies. A command with one needs something the tests lack (real
   data, a checkpoint or a run of the user's): it is *composed* (every override parsed and applied to the
   project's config, the launcher's settings included) but not run; :attr:`Command.needs` says what.
3. A command without one needs nothing the tests lack: it is run on the ``tiny`` preset (``experiment=tiny``)
   with each swept list cut to its first value and the run and cache directories of the test.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass
from pathlib import Path

from tests.helpers import REPO

START = re.compile(r"python -m (semvpr(?:\.[a-z_]+)+)")
PLACEHOLDER = re.compile(r"<[^>]*>|\b[A-Z][A-Z0-9_]*(?:_DIR)?\b(?![a-z])|^/data/|^/shared/|\.\./shared/")
HYDRA_COMMANDS = {
    "semvpr.train": "train",
    "semvpr.eval": "eval",
    "semvpr.localize": "localize",
    "semvpr.segment": "segment",
    "semvpr.label": "label",
}


@dataclass(frozen=True)
class Command:
    """One documented command: where it is, its text, its module and its arguments after rule 1."""

    where: str
    text: str
    module: str
    args: tuple[str, ...]

    @property
    def needs(self) -> str | None:
        """What the command needs that the tests lack (rule 2), None where it runs as it is (rule 3)."""
        if self.module == "semvpr.segment" and not any(a.startswith("seg.root=") for a in self.args):
            return "a segmentation set (seg.root)"
        if self.module == "semvpr.label" and not any(a.startswith("images=") for a in self.args):
            return "a folder of images and a trained teacher (images, teacher.checkpoint)"
        if self.module == "semvpr.reporting.claims":
            return "the repository's own docs (tests/reporting/test_claims.py runs it on them)"
        if self.module in ("semvpr.data.synthcity", "semvpr.report", "semvpr.evaltable") and not self.args:
            return "its arguments (the command is only named)"
        if self.module in ("semvpr.eval", "semvpr.localize") and not any(a.startswith("ckpt=") for a in self.args):
            return "a checkpoint (ckpt)"
        for arg in self.args:
            value = arg.partition("=")[2] if "=" in arg else arg
            if PLACEHOLDER.search(value):
                if "shared/realdata" in value:
                    return f"the real data under {value}"
                return f"a value of the user's: {arg}"
        return None

    @property
    def multirun(self) -> bool:
        return "-m" in self.args or "--multirun" in self.args


def sources() -> list[Path]:
    """The files whose commands are collected."""
    docs = [REPO / "README.md", *REPO.glob("docs/**/*.md"), *REPO.glob("experiments/**/README.md")]
    docs += [*REPO.glob("benchmarks/**/README.md"), *REPO.glob("conf/**/*.yaml")]
    return sorted(p for p in docs if p.is_file())


def _spans(text: str, markdown: bool) -> list[tuple[int, str]]:
    """(line number, text) of every piece of a file that may hold a command: fenced code blocks' lines
    (continuations joined), inline code spans (line breaks inside them joined), and yaml comment lines."""
    found: list[tuple[int, str]] = []
    if not markdown:
        for number, line in enumerate(text.splitlines(), 1):
            comment = line.partition("#")[2]
            found += [(number, span) for span in re.findall(r"`([^`]+)`", comment)] or [(number, comment)]
        return found
    lines, prose, in_block, pending = text.splitlines(), [], False, ""
    for number, line in enumerate(lines, 1):
        if line.lstrip().startswith("```"):
            in_block = not in_block
            prose.append("")
            continue
        if in_block:
            pending += line.rstrip().removesuffix("\\") + " " if line.rstrip().endswith("\\") else line
            if not line.rstrip().endswith("\\"):
                found.append((number, pending))
                pending = ""
            prose.append("")
        else:
            prose.append(line)
    joined = "\n".join(prose)
    for match in re.finditer(r"`([^`]+)`", joined):
        found.append((joined.count("\n", 0, match.start()) + 1, " ".join(match.group(1).split())))
    return found


def _arguments(rest: str) -> tuple[str, ...]:
    """Rule 1 on the text after ``python -m semvpr.<module>``."""
    rest = rest.replace("\\|", "|")
    rest = re.sub(r"<[^<>]*>", lambda m: "_".join(m.group(0).split()), rest)  # <sweep dir>: one placeholder
    try:
        tokens = shlex.split(rest, comments=True)
    except ValueError:  # an unbalanced quote in a note: the words as written
        tokens = rest.split()
    args: list[str] = []
    depth = 0
    for token in tokens:
        if token.startswith("[") and "=" not in token.partition("[")[0]:
            depth += 1
        if depth:
            depth -= token.count("]") > 0 and token.endswith("]")
            continue
        if token in ("...", "[overrides]", "overrides", "…") or token.endswith(("...", "…")):
            continue
        if token in ("&&", "|", ";", "(", ")") or token.startswith(("(", "→")):
            break  # the sentence or the shell line goes on: the command ends here
        key, sep, value = token.partition("=")
        if "|" in value and not value.startswith(("'", '"')):
            token = f"{key}{sep}{value.split('|')[0]}"
        elif "|" in token and not sep:
            token = token.split("|")[0]
        args.append(token)
    return tuple(args)


def collect() -> list[Command]:
    """Every documented command, once per place it is written."""
    commands: list[Command] = []
    for path in sources():
        text = path.read_text(encoding="utf-8")
        for number, span in _spans(text, path.suffix == ".md"):
            for match in START.finditer(span):
                module = match.group(1)
                rest = span[match.end() :]
                following = START.search(rest)
                rest = rest[: following.start()] if following else rest
                where = f"{path.relative_to(REPO)}:{number}"
                commands.append(Command(where, f"python -m {module}{rest}".strip(), module, _arguments(rest)))
    return commands


def first_of_each_sweep(args: tuple[str, ...]) -> list[str]:
    """Rule 3: each swept list cut to its first value (a quoted value with a comma is one value)."""
    out = []
    for arg in args:
        key, sep, value = arg.partition("=")
        if sep and "," in value and not value.startswith(("[", "'", '"')) and not key.startswith("hydra"):
            value = value.split(",")[0]
        out.append(f"{key}{sep}{value}")
    return out


def placeholders(args: tuple[str, ...]) -> list[str]:
    """The arguments whose value is a placeholder (rule 2)."""
    return [a for a in args if PLACEHOLDER.search(a.partition("=")[2] if "=" in a else a)]


def composable(args: tuple[str, ...]) -> list[str]:
    """The arguments with each ``<placeholder>`` replaced by a plain word, so that Hydra parses them; a
    config group chosen by a placeholder (``aggregator=A``) keeps its default."""
    out = []
    for arg in args:
        key, sep, value = arg.partition("=")
        if sep and (REPO / "conf" / key).is_dir() and PLACEHOLDER.search(value):
            continue
        out.append(re.sub(r"<[^<>]*>", "placeholder", arg))
    return out

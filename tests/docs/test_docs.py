"""Every ``ARCHITECTURE §n`` cited in the code names a section that docs/ARCHITECTURE.md has."""

from __future__ import annotations

import re
from pathlib import Path

from tests.helpers import REPO


def test_architecture_references_resolve() -> None:
    doc = (REPO / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    sections = set(re.findall(r"^#{2,3} (\d+(?:\.\d+)?)\.? ", doc, flags=re.M))
    cited: dict[str, list[str]] = {}
    for path in [*REPO.glob("semvpr/**/*.py"), *REPO.glob("conf/**/*.yaml"), *REPO.glob("benchmarks/*.py")]:
        for ref in re.findall(r"ARCHITECTURE §(\d+(?:\.\d+)?)", path.read_text(encoding="utf-8")):
            cited.setdefault(ref, []).append(str(path.relative_to(REPO)))
    assert cited, "the code cites no section: the doc would be unreachable from it"
    missing = {ref: where for ref, where in cited.items() if ref not in sections}
    assert not missing, f"sections cited but absent from docs/ARCHITECTURE.md: {missing}"


def _imported_modules(path: Path) -> set[str]:
    """Absolute semvpr modules a file imports (``from semvpr.x import y`` counts x and x.y)."""
    import ast

    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found |= {node.module, *(f"{node.module}.{alias.name}" for alias in node.names)}
    return {name for name in found if name.startswith("semvpr")}


def test_no_module_imports_an_entry_point() -> None:
    """ARCHITECTURE §1: what two commands share lives below them, never in a command's module."""
    doc = (REPO / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    commands = set(re.findall(r"^\| `python -m (semvpr\.[\w.]+)", doc, flags=re.M))
    # Modules that are a library first and also runnable (a generator, a summary) are not thin commands.
    entry_points = commands - {"semvpr.data.synthcity", "semvpr.data.inspect", "semvpr.reporting.claims"}
    assert {"semvpr.train", "semvpr.eval", "semvpr.report"} <= entry_points, commands
    offenders = {}
    for path in REPO.glob("semvpr/**/*.py"):
        module = ".".join(path.relative_to(REPO).with_suffix("").parts)
        bad = (_imported_modules(path) & entry_points) - {module}
        if bad:
            offenders[module] = sorted(bad)
    assert not offenders, f"modules importing an entry point (move the shared code below it): {offenders}"


def _layers() -> dict[str, int]:
    """ARCHITECTURE §1's layer table, bottom first: package (or command module) → its rank."""
    doc = (REPO / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    table = doc.split("<!-- layers -->")[1]
    ranks: dict[str, int] = {}
    rows = [line for line in table.splitlines() if line.startswith("| ") and "`semvpr" in line]
    for rank, line in enumerate(reversed(rows)):  # the table lists the top layer first
        for name in re.findall(r"`(semvpr[\w.]*)`", line.split("|")[2]):
            ranks[name] = rank
    return ranks


def _layer_of(module: str, ranks: dict[str, int]) -> str | None:
    """The longest layer name that is ``module`` or a package above it."""
    owners = [name for name in ranks if module == name or module.startswith(f"{name}.")]
    return max(owners, key=len) if owners else None


def test_imports_point_down_the_layers() -> None:
    """ARCHITECTURE §1: every module imports only its own layer's modules and those of layers below it."""
    ranks = _layers()
    assert {"semvpr.core", "semvpr.data", "semvpr.models", "semvpr.config", "semvpr.train"} <= set(ranks), ranks
    offenders, unplaced = {}, []
    for path in REPO.glob("semvpr/**/*.py"):
        module = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
        if module == "semvpr":
            continue  # the package's version only
        own = _layer_of(module, ranks)
        if own is None:
            unplaced.append(module)
            continue
        up = sorted(
            name
            for name in _imported_modules(path)
            if (layer := _layer_of(name, ranks)) is not None and ranks[layer] > ranks[own]
        )
        if up:
            offenders[module] = up
    assert not unplaced, f"modules in no layer of ARCHITECTURE §1's table: {unplaced}"
    assert not offenders, f"imports that climb a layer (move the shared code down): {offenders}"


def test_no_module_below_config_reads_a_config() -> None:
    """ARCHITECTURE §1: below ``semvpr.config`` code takes typed values; composing, reading or selecting in a
    config (omegaconf, Hydra) is the config layer's and the commands' work. ``semvpr.data.inspect`` is a command
    that lives beside its data (ARCHITECTURE §1's command table)."""
    import ast

    ranks = _layers()
    below = {name for name, rank in ranks.items() if rank < ranks["semvpr.config"]}
    offenders = {}
    for path in REPO.glob("semvpr/**/*.py"):
        module = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
        if _layer_of(module, ranks) not in below or module == "semvpr.data.inspect":
            continue
        found = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                found |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.add(node.module.split(".")[0])
        if found & {"omegaconf", "hydra"}:
            offenders[module] = sorted(found & {"omegaconf", "hydra"})
    assert below >= {"semvpr.core", "semvpr.data", "semvpr.models", "semvpr.reporting"}, below
    assert not offenders, f"modules below semvpr.config that read a config (move that work up): {offenders}"


def test_the_top_of_the_package_holds_the_commands() -> None:
    """The top of semvpr/ holds the commands (and the hub), everything else lives in a role's folder."""
    top = sorted(p.stem for p in (REPO / "semvpr").glob("*.py") if p.stem != "__init__")
    assert len(top) <= 10, top
    commands = set(
        re.findall(r"^\| `python -m semvpr\.(\w+)", (REPO / "docs" / "ARCHITECTURE.md").read_text(), flags=re.M)
    )
    assert set(top) <= commands | {"hub"}, set(top) - commands


def test_committed_results_carry_no_absolute_path_of_the_machine_that_made_them() -> None:
    """The report writes no sweep path (a results.md is read on other machines); the committed ones agree."""
    pattern = re.compile(r"(?<![\w.])/(?:work|home|tmp|root|Users|mnt|data)/")
    found = {
        str(path.relative_to(REPO)): line
        for path in REPO.glob("experiments/**/results.md")
        for line in path.read_text(encoding="utf-8").splitlines()
        if pattern.search(line)
    }
    assert not found, found


def _tracked_files() -> set[str]:
    """The repository's committed files (the ones a clone has), relative to the root, with / separators."""
    import subprocess

    try:
        out = subprocess.run(
            ["git", "-C", str(REPO), "ls-files", "-z"], capture_output=True, check=True, timeout=600
        ).stdout
    except (OSError, subprocess.SubprocessError):
        out = b""
    names = {name for name in out.decode("utf-8").split("\0") if name}
    if names:
        return names
    # No git (an unpacked archive): everything on disk outside hidden, built and output folders.
    skip = {"outputs", "multirun", "lightning_logs", "__pycache__"}
    return {
        path.relative_to(REPO).as_posix()
        for path in REPO.rglob("*")
        if path.is_file() and not any(p.startswith(".") or p in skip for p in path.relative_to(REPO).parts[:-1])
    }


def _github_anchors(markdown: str) -> set[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation dropped, spaces to hyphens."""
    anchors: set[str] = set()
    for heading in re.findall(r"^#{1,6} +(.+?) *#* *$", _without_code_blocks(markdown), flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        candidate, n = slug, 0
        while candidate in anchors:
            n += 1
            candidate = f"{slug}-{n}"
        anchors.add(candidate)
    return anchors


def _without_code_blocks(markdown: str) -> str:
    """The text outside fenced code blocks (a link inside one is an example, not a link)."""
    return re.sub(r"^ *```.*?^ *```", "", markdown, flags=re.M | re.S)


def test_markdown_links_resolve() -> None:
    """Every relative link and image in every committed .md file names a committed file, and its
    #anchor a heading of that file: a reader of a clone never meets a broken link or image."""
    tracked = _tracked_files()
    folders = {"/".join(name.split("/")[:i]) for name in tracked for i in range(1, name.count("/") + 1)}
    pages = sorted(name for name in tracked if name.endswith(".md"))
    assert "README.md" in pages, pages
    link = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
    broken = []
    for page in pages:
        text = _without_code_blocks((REPO / page).read_text(encoding="utf-8"))
        text = re.sub(r"`[^`\n]*`", "", text)  # inline code
        for target in link.findall(text):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, flags=re.I):  # https:, mailto: ...
                continue
            path, _, anchor = target.partition("#")
            if path:
                resolved = (Path(page).parent / path).as_posix()
                parts: list[str] = []
                for part in resolved.split("/"):
                    if part == "..":
                        if not parts:
                            parts.append("..")  # climbs out of the repository: never resolves
                        else:
                            parts.pop()
                    elif part not in ("", "."):
                        parts.append(part)
                resolved = "/".join(parts).rstrip("/")
                if resolved not in tracked and resolved not in folders:
                    broken.append(f"{page}: {target} (no committed file {resolved})")
                    continue
            else:
                resolved = page
            if (
                anchor
                and resolved.endswith(".md")
                and anchor not in _github_anchors((REPO / resolved).read_text(encoding="utf-8"))
            ):
                broken.append(f"{page}: {target} (no heading #{anchor} in {resolved})")
    assert not broken, "broken links:\n" + "\n".join(broken)

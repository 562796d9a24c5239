"""Every result the committed docs state is held to a committed data file (docs/trust.md, "Numbers in
the docs"): numbers inside a claim marker must be in its sources, a generated table must equal what its
CSV renders, and a result-like number outside every marker fails unless ``claims.NOT_RESULTS`` names it as a
hyper-parameter, a version or a definition."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from semvpr.core.errors import SemvprError
from semvpr.reporting import claims
from tests.helpers import REPO

DOCS = claims.committed_docs(REPO)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_marked_numbers_match_their_sources(doc: Path) -> None:
    problems = claims.check_markdown(doc, REPO)
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_no_result_without_a_source(doc: Path) -> None:
    loose = claims.unsourced_numbers(doc.read_text(encoding="utf-8"))
    assert not loose, "results outside a claim marker (mark them with their data file, or drop them):\n" + "\n".join(
        f"{doc.relative_to(REPO)}:{s.line}: {s.text}" for s in loose
    )


def test_the_committed_docs_mark_claims() -> None:
    """The markers are in use where the front page states results (not an empty check)."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    kinds = {span.kind for span in claims.marked_spans(readme)}
    assert kinds == {"claim", "table"}, kinds


def _write(tmp_path: Path, markdown: str) -> Path:
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "r.csv").write_text(
        "aggregator,mask,R@1_mean,R@1_std,gain\nnetvlad,none,70.6032,1.3345,\nsral,student,78.9841,1.1481,+8.4\n",
        encoding="utf-8",
    )
    doc = tmp_path / "doc.md"
    doc.write_text(markdown, encoding="utf-8")
    return doc


def test_a_right_claim_passes(tmp_path: Path) -> None:
    text = "NetVLAD 70.6 ± 1.3, the student +8.4 (79.0 %)."
    doc = _write(tmp_path, f"<!-- claim: data/r.csv -->\n{text}\n<!-- /claim -->\n")
    assert claims.check_markdown(doc, tmp_path) == []


@pytest.mark.parametrize(
    "wrong",
    [
        "NetVLAD 70.8 ± 1.3",  # a typo in the last digit
        "NetVLAD 70.61 ± 1.3",  # a stated extra decimal is held to it (70.6032 is not 70.61)
        "the student −8.4",  # the sign is part of a signed claim
        "the student +8.4 in 78.9 %",  # 78.98 rounds to 79.0, not 78.9
    ],
)
def test_a_wrong_number_in_a_claim_fails(tmp_path: Path, wrong: str) -> None:
    doc = _write(tmp_path, f"<!-- claim: data/r.csv -->\n{wrong}.\n<!-- /claim -->\n")
    problems = claims.check_markdown(doc, tmp_path)
    assert problems and all(p.startswith("doc.md:2: ") for p in problems), problems


@pytest.mark.parametrize(
    "mixed",
    [
        "NetVLAD 70.6 ± 1.1",  # 1.1 is a std, but the student's: a mean and its std come from one row, side by side
        "| netvlad | 70.6 ± 1.3 / 79.0 |",  # one table cell's numbers come from one row
    ],
)
def test_numbers_written_together_come_from_one_record(tmp_path: Path, mixed: str) -> None:
    doc = _write(tmp_path, f"<!-- claim: data/r.csv -->\n{mixed}\n<!-- /claim -->\n")
    problems = claims.check_markdown(doc, tmp_path)
    assert problems and all("not side by side" in p or "not from one record" in p for p in problems), problems


def test_an_unsigned_magnitude_matches_a_loss(tmp_path: Path) -> None:
    doc = _write(tmp_path, "<!-- claim: data/r.csv -->\na gain of 8.4 points\n<!-- /claim -->\n")
    assert claims.check_markdown(doc, tmp_path) == []


def test_a_generated_table_is_checked_and_rewritten(tmp_path: Path) -> None:
    table = "| aggregator · mask | R@1 |\n|---|---:|\n| netvlad · none | 70.6 ± 1.3 |\n| sral · student | 79.0 ± 1.1 |"
    doc = _write(tmp_path, f"<!-- table: data/r.csv aggregator,mask R@1 -->\n{table}\n<!-- /table -->\n")
    assert claims.check_markdown(doc, tmp_path) == []
    doc.write_text(doc.read_text(encoding="utf-8").replace("79.0 ± 1.1", "79.1 ± 1.1"), encoding="utf-8")
    assert [p for p in claims.check_markdown(doc, tmp_path) if "table differs from data/r.csv" in p]
    assert claims.write_tables(doc, tmp_path)
    assert claims.check_markdown(doc, tmp_path) == []
    assert table in doc.read_text(encoding="utf-8")


def test_a_result_outside_a_marker_is_flagged(tmp_path: Path) -> None:
    marked = "<!-- claim: data/r.csv -->\n70.6\n<!-- /claim -->\n"
    text = "New: 81.2 R@1, +3 over none, 12 %, in 95 s.\n`lr 0.5` 16 epochs, 3 seeds, stage4, 180x240\n"
    doc = _write(tmp_path, marked + text)
    loose = claims.unsourced_numbers(doc.read_text(encoding="utf-8"))
    assert [(s.text, s.line) for s in loose] == [("81.2", 4), ("+3", 4), ("12 %", 4), ("95 s", 4)]


def test_a_marker_opening_a_line_of_text_is_flagged(tmp_path: Path) -> None:
    doc = _write(tmp_path, "Text <!-- claim: data/r.csv -->70.6\n<!-- /claim --> and more\n")
    assert claims.check_markdown(doc, tmp_path) == [
        "doc.md:2: a marker opens this line of text, which would render as raw HTML (move it up a line)"
    ]


def test_a_marker_without_its_end_or_source_is_one_error(tmp_path: Path) -> None:
    doc = _write(tmp_path, "<!-- claim: data/r.csv -->\n70.6\n")
    with pytest.raises(SemvprError, match="without its '<!-- /claim -->'"):
        claims.check_markdown(doc, tmp_path)
    doc.write_text("<!-- claim: data/missing.csv -->\n70.6\n<!-- /claim -->\n", encoding="utf-8")
    with pytest.raises(SemvprError, match="no such data file"):
        claims.check_markdown(doc, tmp_path)


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "semvpr.reporting.claims", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


def test_the_command_checks_the_committed_docs() -> None:
    proc = _run(cwd=REPO)
    assert proc.returncode == 0 and "every stated number holds" in proc.stdout, (proc.stdout, proc.stderr)


def test_the_command_names_each_problem_and_rewrites_tables(tmp_path: Path) -> None:
    stale = "| aggregator · mask | R@1 |\n|---|---:|\n| netvlad · none | 70.0 ± 1.3 |"
    doc = _write(
        tmp_path,
        f"<!-- table: data/r.csv aggregator,mask R@1 -->\n{stale}\n<!-- /table -->\n"
        "<!-- claim: data/r.csv -->\nthe student +8.5\n<!-- /claim -->\nand 81.2 R@1 unmarked\n",
    )
    proc = _run("--root", str(tmp_path), str(doc), cwd=tmp_path)
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    assert proc.stdout.splitlines() == [
        "doc.md:1: table differs from data/r.csv (regenerate it)",
        "doc.md:7: +8.5 is in no source of its claim (data/r.csv)",
        "doc.md:9: 81.2 is outside every claim marker",
    ], proc.stdout
    proc = _run("--write", "--root", str(tmp_path), str(doc), cwd=tmp_path)
    assert "79.0 ± 1.1" in doc.read_text(encoding="utf-8") and "table differs" not in proc.stdout, proc.stdout


def test_a_json_pointer_narrows_a_source(tmp_path: Path) -> None:
    (tmp_path / "r.json").write_text('{"teacher": {"car": 0.85}, "student": {"car": 0.81}}', encoding="utf-8")
    doc = tmp_path / "doc.md"
    doc.write_text("<!-- claim: r.json#/teacher -->\ncar IoU 0.85\n<!-- /claim -->\n", encoding="utf-8")
    assert claims.check_markdown(doc, tmp_path) == []
    doc.write_text("<!-- claim: r.json#/teacher -->\ncar IoU 0.81\n<!-- /claim -->\n", encoding="utf-8")
    assert claims.check_markdown(doc, tmp_path) == ["doc.md:2: 0.81 is in no source of its claim (r.json#/teacher)"]
    doc.write_text("<!-- claim: r.json#/teacher/bus -->\n0.81\n<!-- /claim -->\n", encoding="utf-8")
    with pytest.raises(SemvprError, match="no '/teacher/bus' in it"):
        claims.check_markdown(doc, tmp_path)


@pytest.mark.parametrize(
    ("script", "report"),
    [
        *(("experiments/report_gains.py", p.relative_to(REPO)) for p in sorted(REPO.glob("experiments/**/gains.csv"))),
        ("experiments/real-streets/results_csv.py", Path("experiments/real-streets/results.csv")),
    ],
    ids=str,
)
def test_a_derived_data_file_is_what_its_script_makes_of_the_report(tmp_path: Path, script: str, report: Path) -> None:
    """gains.csv and the real-streets results.csv are read back from the committed results.md: rerunning the
    script on that results.md gives the committed file, byte for byte."""
    copy = tmp_path / "results.md"
    copy.write_text((REPO / report).with_name("results.md").read_text(encoding="utf-8"), encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, str(REPO / script), str(copy)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / report.name).read_bytes() == (REPO / report).read_bytes()


def test_gains_are_read_from_every_form_the_report_writes() -> None:
    """The two sentences semvpr.report writes, with a comma inside a label's parentheses and a loss."""
    sys.path.insert(0, str(REPO / "experiments"))
    try:
        from report_gains import gains
    finally:
        sys.path.remove(str(REPO / "experiments"))
    report = (
        "**R@1 gain over none (netvlad · none) (resnet50)**, per seed, then mean ± std: oracle (sral · oracle, "
        "upper bound) +8.0 ± 2.2 (better in 3 of 3 seeds), unet (sral · student) −0.3 ± 2.7 (better in 1 of 3 seeds)\n"
        "## Aggregator × mask (resnet50)\n"
        "- boq (gsv): student +4.8 ± 0.7 (better in 3 of 3 seeds)\n"
    )
    assert [
        (r["section"], r["baseline"], r["model"], r["gain_mean"], r["gain_std"], r["seeds_better"])
        for r in gains(report)
    ] == [
        ("main", "over none (netvlad · none) (resnet50)", "oracle (sral · oracle, upper bound)", "+8.0", "2.2", "3"),
        ("main", "over none (netvlad · none) (resnet50)", "unet (sral · student)", "-0.3", "2.7", "1"),
        ("Aggregator × mask (resnet50)", "boq (gsv) · none", "student", "+4.8", "0.7", "3"),
    ]

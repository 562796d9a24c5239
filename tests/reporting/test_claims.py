"""Every result the committed docs state is generated from a committed data file (docs/trust.md, "Numbers
in the docs"): a value marker holds what its row gives, a table what its source renders, a count the rows
its conditions keep, and a result-like number outside every marker fails."""

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
    assert not loose, "results outside every marker (generate them from their data file, or drop them):\n" + "\n".join(
        f"{doc.relative_to(REPO)}:{s.line}: {s.text}" for s in loose
    )


def test_the_committed_docs_mark_claims() -> None:
    """The markers are in use where the front page states results (not an empty check)."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    kinds = {span.kind for span in claims.marked_spans(readme)}
    assert kinds == {"value", "table"}, kinds


def _write(tmp_path: Path, markdown: str) -> Path:
    (tmp_path / "data").mkdir(exist_ok=True)
    (tmp_path / "data" / "r.csv").write_text(
        "aggregator,mask,R@1_mean,R@1_std,gain,seeds\nnetvlad,none,70.6032,1.3345,,3\n"
        "sral,student,78.9841,1.1481,+8.4,3\nsral,teacher,78.2,0.9,-0.8,3\n",
        encoding="utf-8",
    )
    doc = tmp_path / "doc.md"
    doc.write_text(markdown, encoding="utf-8")
    return doc


def _value(conditions: str, template: str, text: str) -> str:
    return f"<!-- value: data/r.csv {conditions} '{template}' -->{text}<!-- /value -->"


def test_a_value_is_what_its_row_gives(tmp_path: Path) -> None:
    text = (
        f"NetVLAD {_value('aggregator=netvlad', '{R@1_mean:.1f} ± {R@1_std:.1f}', '70.6 ± 1.3')}, the student "
        f"{_value('mask=student', '{gain:+.1f}', '+8.4')} ({_value('mask=student', '{R@1_mean:.1f} %', '79.0 %')}), "
        f"the teacher's loss {_value('mask=teacher', '{-gain:.1f}', '0.8')} points.\n"
    )
    assert claims.check_markdown(_write(tmp_path, text), tmp_path) == []


@pytest.mark.parametrize(
    ("conditions", "template", "wrong"),
    [
        ("aggregator=netvlad", "{R@1_mean:.1f} ± {R@1_std:.1f}", "70.8 ± 1.3"),  # a typo in the last digit
        ("aggregator=netvlad", "{R@1_mean:.1f}", "70.61"),  # an extra decimal is not what the template gives
        ("mask=student", "{gain:+.1f}", "−8.4"),  # the sign is the data's
        ("mask=teacher", "{R@1_mean:.1f} ± {R@1_std:.1f}", "79.0 ± 1.1"),  # the student's numbers, the teacher's row
    ],
)
def test_a_wrong_value_fails(tmp_path: Path, conditions: str, template: str, wrong: str) -> None:
    doc = _write(tmp_path, f"Said:\nit was {_value(conditions, template, wrong)}.\n")
    (problem,) = claims.check_markdown(doc, tmp_path)
    assert problem.startswith(f"doc.md:2: {wrong!r} is not ") and "what data/r.csv gives" in problem, problem


@pytest.mark.parametrize(
    ("conditions", "error"),
    [
        ("aggregator=sral", "aggregator=sral keeps rows that differ"),  # two rows: which one is said?
        ("mask=oracle", "mask=oracle keeps no row"),
        ("masks=student", "no column 'masks'"),
    ],
)
def test_a_value_names_its_row(tmp_path: Path, conditions: str, error: str) -> None:
    doc = _write(tmp_path, f"Said: {_value(conditions, '{R@1_mean:.1f}', '79.0')}.\n")
    (problem,) = claims.check_markdown(doc, tmp_path)
    assert problem.startswith("doc.md:1: ") and error in problem, problem


def test_rows_that_agree_give_one_value(tmp_path: Path) -> None:
    """A setting shared by the rows a condition keeps (every run's seeds) is one value."""
    doc = _write(tmp_path, f"Over {_value('aggregator=sral', '{seeds:.0f} seeds', '3 seeds')}.\n")
    assert claims.check_markdown(doc, tmp_path) == []


def test_generated_tables_and_values_are_checked_and_rewritten(tmp_path: Path) -> None:
    table = (
        "| aggregator · mask | R@1 |\n|---|---:|\n| netvlad · none | 70.6 ± 1.3 |\n| sral · student | 79.0 ± 1.1 |\n"
        "| sral · teacher | 78.2 ± 0.9 |"
    )
    value = _value("mask=student", "{gain:+.1f}", "+8.4")
    doc = _write(tmp_path, f"<!-- table: data/r.csv aggregator,mask R@1 -->\n{table}\n<!-- /table -->\nGain {value}.\n")
    assert claims.check_markdown(doc, tmp_path) == []
    stale = doc.read_text(encoding="utf-8").replace("79.0 ± 1.1", "79.1 ± 1.1").replace("+8.4<", "+8.5<")
    doc.write_text(stale, encoding="utf-8")
    assert len(claims.check_markdown(doc, tmp_path)) == 2
    assert claims.write_generated(doc, tmp_path)
    assert claims.check_markdown(doc, tmp_path) == []
    assert table in doc.read_text(encoding="utf-8") and value in doc.read_text(encoding="utf-8")


def test_a_result_outside_a_marker_is_flagged(tmp_path: Path) -> None:
    marked = _value("aggregator=netvlad", "{R@1_mean:.1f}", "70.6") + "\n## 3.1 A section, §3.4\n"
    text = "New: 81.2 R@1, +3 over none, 12 %, in 95 s.\n`lr 0.5` 16 epochs, 3 seeds, stage4, 180x240, 95-percent\n"
    doc = _write(tmp_path, marked + text)
    loose = claims.unsourced_numbers(doc.read_text(encoding="utf-8"))
    assert [(s.text, s.line) for s in loose] == [("81.2", 3), ("+3", 3), ("12 %", 3), ("95 s", 3)]


def test_a_marker_opening_a_line_of_text_is_flagged(tmp_path: Path) -> None:
    doc = _write(tmp_path, "Text\n" + _value("aggregator=netvlad", "{R@1_mean:.1f}", "70.6") + " and more\n")
    assert claims.check_markdown(doc, tmp_path) == [
        "doc.md:2: a marker opens this line of text, which would render as raw HTML (move it up a line)"
    ]


def test_a_marker_without_its_end_or_source_is_one_error(tmp_path: Path) -> None:
    doc = _write(tmp_path, "Text <!-- value: data/r.csv mask=student '{gain:+.1f}' -->+8.4\n")
    with pytest.raises(SemvprError, match="without its '<!-- /value -->'"):
        claims.check_markdown(doc, tmp_path)
    doc.write_text("Text <!-- value: data/missing.csv '{gain}' -->70.6<!-- /value -->\n", encoding="utf-8")
    (problem,) = claims.check_markdown(doc, tmp_path)
    assert problem.startswith("doc.md:1: ") and "no such data file" in problem, problem
    doc.write_text("Text <!-- value: data/r.csv mask=student -->70.6<!-- /value -->\n", encoding="utf-8")
    (problem,) = claims.check_markdown(doc, tmp_path)
    assert "expected '<!-- value: SOURCE [CONDITION ...] TEMPLATE -->'" in problem, problem


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "semvpr.reporting.claims", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
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
        f"the student {_value('mask=student', '{gain:+.1f}', '+8.5')}\nand 81.2 R@1 unmarked\n",
    )
    proc = _run("--root", str(tmp_path), str(doc), cwd=tmp_path)
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    assert proc.stdout.splitlines() == [
        "doc.md:1: table differs from data/r.csv (regenerate it)",
        "doc.md:6: '+8.5' is not '+8.4', what data/r.csv gives (regenerate it)",
        "doc.md:7: 81.2 is a result outside every value, table and count marker",
    ], proc.stdout
    proc = _run("--write", "--root", str(tmp_path), str(doc), cwd=tmp_path)
    text = doc.read_text(encoding="utf-8")
    assert "79.0 ± 1.1" in text and "+8.4<" in text and "differs" not in proc.stdout, proc.stdout


def test_a_json_value_names_its_field(tmp_path: Path) -> None:
    """Without conditions a JSON part is one row, its fields by dotted path (lists by index); a pointer
    narrows it."""
    (tmp_path / "r.json").write_text(
        '{"teacher": {"car": 0.85, "per_seed": [0.5, 0.7]}, "student": {"car": 0.81}}', encoding="utf-8"
    )
    doc = tmp_path / "doc.md"
    marked = (
        "car IoU <!-- value: r.json '{teacher.car:.2f}' -->0.85<!-- /value -->, seed 1 "
        "<!-- value: r.json '{teacher.per_seed.1:.1f}' -->0.7<!-- /value -->, the student's "
        "<!-- value: r.json#/student '{car:.2f}' -->0.81<!-- /value -->\n"
    )
    doc.write_text(marked, encoding="utf-8")
    assert claims.check_markdown(doc, tmp_path) == []
    doc.write_text(marked.replace("-->0.85<", "-->0.81<"), encoding="utf-8")
    assert claims.check_markdown(doc, tmp_path) == ["doc.md:1: '0.81' is not '0.85', what r.json gives (regenerate it)"]
    doc.write_text("x <!-- value: r.json#/teacher/bus '{car}' -->0.81<!-- /value -->\n", encoding="utf-8")
    (problem,) = claims.check_markdown(doc, tmp_path)
    assert problem.startswith("doc.md:1: ") and "no '/teacher/bus' in it" in problem, problem


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
        timeout=600,
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


def _pairs(tmp_path: Path) -> None:
    (tmp_path / "p.csv").write_text(
        "pair,model,mask,seeds,R@1_mean,R@1_std,gain,ci_low,ci_high,excludes_0\n"
        "night,gem,none,1,37.5,,,,,\n"
        "night,gem,camvid,1,34.5,,-3.0,-7.0,+1.0,no\n"
        "night,netvlad,none,3,54.7,1.3,,,,\n"
        "night,netvlad,camvid,3,53.8,1.8,-3.3,-6.3,-0.3,yes\n"
        "day,gem,none,1,87.0,,,,,\n"
        "day,gem,camvid,1,89.5,,+2.5,-0.5,+6.0,no\n"
        "day,netvlad,none,3,92.2,0.8,,,,\n"
        "day,netvlad,camvid,3,94.5,0.5,+2.3,+0.8,+4.2,yes\n",
        encoding="utf-8",
    )


_PIVOT = (
    '<!-- table: p.csv model,mask pivot=pair "where=model!=gem" '
    '"col=R@1={R@1_mean:.1f}[[ ± {R@1_std:.1f}]][[ ({gain:+.1f} [{ci_low:+.1f}, {ci_high:+.1f}]{excludes_0? *})]]"'
    " -->\n"
)


def test_a_pivoted_table_with_templates_is_generated_and_checked(tmp_path: Path) -> None:
    """A field's values as columns, rows kept by a condition, the first alternative whose fields all have
    a value, a flag, the typographic minus; a stale or wrong cell fails, and --write repairs it."""
    _pairs(tmp_path)
    table = (
        "| model · mask | night | day |\n|---|---:|---:|\n| netvlad · none | 54.7 ± 1.3 | 92.2 ± 0.8 |\n"
        "| netvlad · camvid | 53.8 ± 1.8 (−3.3 [−6.3, −0.3] *) | 94.5 ± 0.5 (+2.3 [+0.8, +4.2] *) |"
    )
    doc = tmp_path / "doc.md"
    doc.write_text(f"{_PIVOT}{table}\n<!-- /table -->\n", encoding="utf-8")
    assert claims.check_markdown(doc, tmp_path) == []
    for wrong in ("(−3.3 [−6.3, −0.3] *)", "(+2.3 [+0.8, +4.2] *)", "54.7 ± 1.3"):
        doc.write_text(f"{_PIVOT}{table.replace(wrong, wrong.replace('3', '4'))}\n<!-- /table -->\n", encoding="utf-8")
        assert claims.check_markdown(doc, tmp_path) == ["doc.md:1: table differs from p.csv (regenerate it)"]
    assert claims.write_generated(doc, tmp_path) and table in doc.read_text(encoding="utf-8")
    one_seed = _PIVOT.replace('"where=model!=gem" ', '"where=model=gem" "rows=gem · camvid" ')
    doc.write_text(f"{one_seed}\n<!-- /table -->\n", encoding="utf-8")
    claims.write_generated(doc, tmp_path)
    assert "| gem · camvid | 34.5 (−3.0 [−7.0, +1.0]) | 89.5 (+2.5 [−0.5, +6.0]) |" in doc.read_text(encoding="utf-8")


def test_a_json_source_gives_rows_and_several_sources_join(tmp_path: Path) -> None:
    """An object of objects is one row per member (``key``), nested fields dotted; a missing value is –;
    ``as=`` relabels; sources joined by + name themselves in ``source``."""
    (tmp_path / "r.json").write_text(
        '{"teacher": {"miou": 0.6349, "removed": 0.8774, "val": {"miou": 0.7324}}, "student": {"removed": 0.8364},'
        ' "note": "x"}',
        encoding="utf-8",
    )
    marker = (
        '<!-- table: r.json key head=model "as=teacher=the teacher" "col=mIoU={miou:.3f}" "col=val={val.miou:.2f}"'
        ' "col=removed={removed:.1%}" -->\n'
    )
    table = (
        "| model | mIoU | val | removed |\n|---|---:|---:|---:|\n| the teacher | 0.635 | 0.73 | 87.7 % |\n"
        "| student | – | – | 83.6 % |"
    )
    doc = tmp_path / "doc.md"
    doc.write_text(f"{marker}{table}\n<!-- /table -->\n", encoding="utf-8")
    assert claims.check_markdown(doc, tmp_path) == []
    doc.write_text(f"{marker}{table.replace('87.7 %', '87.8 %')}\n<!-- /table -->\n", encoding="utf-8")
    assert claims.check_markdown(doc, tmp_path) == ["doc.md:1: table differs from r.json (regenerate it)"]
    _pairs(tmp_path)
    (tmp_path / "q.csv").write_text("pair,model,mask,R@1_mean,R@1_std\nnight,netvlad,none,60.0,1.0\n", encoding="utf-8")
    joined = '<!-- table: p.csv+q.csv model pivot=source "as=p.csv=before" "as=q.csv=after" "where=pair=night" '
    joined += '"where=mask=none" R@1 -->\n'
    doc.write_text(f"{joined}<!-- /table -->\n", encoding="utf-8")
    claims.write_generated(doc, tmp_path)
    expected = "| model | before | after |\n|---|---:|---:|\n| gem | 37.5 | – |\n| netvlad | 54.7 ± 1.3 | 60.0 ± 1.0 |"
    assert expected in doc.read_text(encoding="utf-8")


@pytest.mark.parametrize(
    ("marker", "error"),
    [
        ('<!-- table: p.csv model "col=R@1={R@1:.1f}" -->', "no column 'R@1'"),
        ('<!-- table: p.csv model,mask pivot=pair "rows=boq · none" R@1 -->', "no row 'boq · none'"),
        ('<!-- table: p.csv model,mask "where=gain<x" R@1 -->', "compares with a number"),
        ("<!-- table: p.csv model pivot=pair R@1 -->", "two rows for 'gem'"),
        ("<!-- table: p.csv model -->", "needs METRICS or a col"),
        ('<!-- table: p.csv model,pair "col=m={mask:.1f}" -->', "expected a number in the data file, got 'none'"),
        ("<!-- count: p.csv mask=none seedz=3 -->4<!-- /count -->", "no column 'seedz'"),
        ('<!-- table: p.csv model "col=m={R@1_mean:.1q}" -->', "{:.1q} is not a number format"),
    ],
)
def test_a_marker_that_cannot_be_rendered_or_counted_is_one_error(tmp_path: Path, marker: str, error: str) -> None:
    """Its file and line, and the markers after it still checked (here a value its row does not give)."""
    _pairs(tmp_path)
    doc = tmp_path / "doc.md"
    bad = f"{marker}\n<!-- /table -->\n" if "table:" in marker else f"{marker}\n"
    after = "R@1 <!-- value: p.csv pair=day model=gem mask=none '{R@1_mean:.1f}' -->99.9<!-- /value -->"
    doc.write_text(f"{bad}\n{after}\n", encoding="utf-8")
    problems = claims.check_markdown(doc, tmp_path)
    assert len(problems) == 2 and any(
        p.endswith("'99.9' is not '87.0', what p.csv gives (regenerate it)") for p in problems
    )
    assert any(p.startswith("doc.md:1: ") and error in p for p in problems), problems


@pytest.mark.parametrize(
    ("count", "holds"),
    [
        ('<!-- count: p.csv mask=camvid "gain<0" excludes_0=yes -->one<!-- /count -->', True),
        ('<!-- count: p.csv mask=camvid "gain<0" excludes_0=yes -->1<!-- /count -->', True),
        ('<!-- count: p.csv mask=camvid "gain<0" excludes_0=yes -->two<!-- /count -->', False),
        ('<!-- count: p.csv "mask=camvid|none" "model~net" -->4<!-- /count -->', True),
        ('<!-- count: p.csv "mask=camvid|none" "model!~net" -->4<!-- /count -->', True),
        ('<!-- count: p.csv mask=camvid "gain>0" -->3<!-- /count -->', False),
        ('<!-- count: p.csv "pair!=day" -->4<!-- /count -->', True),
    ],
)
def test_a_count_is_the_number_of_rows_its_conditions_keep(tmp_path: Path, count: str, holds: bool) -> None:
    """A plain integer in prose held to a query over its source."""
    _pairs(tmp_path)
    doc = tmp_path / "doc.md"
    doc.write_text(f"Of the comparisons, {count} lost.\n", encoding="utf-8")
    problems = claims.check_markdown(doc, tmp_path)
    assert problems == [] if holds else (len(problems) == 1 and "is not the" in problems[0]), problems


def test_a_table_pivots_on_several_fields_in_chosen_groups(tmp_path: Path) -> None:
    """``pivot=F,G`` groups columns by both fields' values; ``groups=`` picks and orders them as shown,
    after ``as=`` (whose value and label may both hold ``=``)."""
    _pairs(tmp_path)
    marker = (
        "<!-- table: p.csv model pivot=pair,mask 'groups=day · camvid|night masked=yes' "
        "'as=night · camvid=night masked=yes' 'as=gem=GeM (`p=3`)' 'col=R@1={R@1_mean:.1f}' -->\n"
    )
    doc = tmp_path / "doc.md"
    doc.write_text(f"{marker}<!-- /table -->\n", encoding="utf-8")
    claims.write_generated(doc, tmp_path)
    expected = (
        "| model | day · camvid | night masked=yes |\n|---|---:|---:|\n| GeM (`p=3`) | 89.5 | 34.5 |\n"
        "| netvlad | 94.5 | 53.8 |"
    )
    assert expected in doc.read_text(encoding="utf-8")
    doc.write_text(f"{marker.replace('day · camvid|', 'dusk · camvid|')}<!-- /table -->\n", encoding="utf-8")
    (problem,) = claims.check_markdown(doc, tmp_path)
    assert "no group 'dusk · camvid'" in problem, problem


@pytest.mark.parametrize(("text", "holds"), [("+4.4 (3 of 3)", True), ("+4.4 (2 of 3)", False)])
def test_n_of_m_is_a_pair_of_fields_of_one_row(tmp_path: Path, text: str, holds: bool) -> None:
    """``N of M`` (seeds better) is what the row's two fields give, exactly."""
    (tmp_path / "g.csv").write_text(
        "model,gain_mean,gain_std,seeds_better,seeds\nstudent,+4.4,4.0,3,3\nteacher,+1.9,2.6,1,3\n", encoding="utf-8"
    )
    doc = tmp_path / "doc.md"
    value = (
        f"<!-- value: g.csv model=student '{{gain_mean:+.1f}} ({{seeds_better}} of {{seeds}})' -->{text}<!-- /value -->"
    )
    doc.write_text(f"The mask gains {value}.\n", encoding="utf-8")
    problems = claims.check_markdown(doc, tmp_path)
    assert (
        problems == []
        if holds
        else problems == ["doc.md:1: '+4.4 (2 of 3)' is not '+4.4 (3 of 3)', what g.csv gives (regenerate it)"]
    )

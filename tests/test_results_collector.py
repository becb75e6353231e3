"""benchmarks/collect_results.py on this repository: RESULTS.md in the fixed order, every results file in a section,
no line over 300 characters, the committed RESULTS.md up to date, and an unlisted or missing file refused."""

from __future__ import annotations

import importlib.util
import re
import shutil
import sys
from pathlib import Path
from types import ModuleType

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def collector() -> ModuleType:
    spec = importlib.util.spec_from_file_location("collect_results", BENCHMARKS / "collect_results.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["collect_results"] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


def test_sections_come_in_the_fixed_order(collector: ModuleType) -> None:
    text = collector.collect()
    anchors = re.findall(r'^<a id="([a-z_0-9]+)"></a>$', text, flags=re.M)
    assert anchors == [s.key for s in collector.SECTIONS]
    summary_links = re.findall(r"^\| \[[^]]+\]\(#([a-z_0-9]+)\)", text, flags=re.M)
    assert summary_links == anchors
    assert text.index("| section |") < text.index('<a id="')  # the summary table comes first


def test_every_results_file_is_in_a_section(collector: ModuleType) -> None:
    listed = {name for s in collector.SECTIONS for name in s.files} | set(collector.NOT_SECTIONS)
    present = {p.relative_to(collector.RESULTS_DIR).as_posix() for p in collector.RESULTS_DIR.rglob("*") if p.is_file()}
    assert present == listed
    assert len({s.key for s in collector.SECTIONS}) == len(collector.SECTIONS)


def test_no_line_is_over_300_characters(collector: ModuleType) -> None:
    lines = collector.collect().splitlines()
    assert max(len(line) for line in lines) <= 300
    committed = (BENCHMARKS / "RESULTS.md").read_text().splitlines()
    assert max(len(line) for line in committed) <= 300


def test_committed_results_md_is_what_the_results_make(collector: ModuleType) -> None:
    assert (BENCHMARKS / "RESULTS.md").read_text() == collector.collect(), "run python benchmarks/collect_results.py"


def test_an_unlisted_or_missing_results_file_is_refused(collector: ModuleType, tmp_path: Path) -> None:
    results = tmp_path / "results"
    shutil.copytree(collector.RESULTS_DIR, results)
    (results / "new_bench.md").write_text("# New\n\n- date: 2026-11-27 12:00 UTC\n")
    with pytest.raises(collector.ResultsError, match="new_bench.md"):
        collector.collect(results)
    (results / "new_bench.md").unlink()
    (results / "sim.md").unlink()
    with pytest.raises(collector.ResultsError, match="sim.md"):
        collector.collect(results)


def test_a_table_row_over_300_characters_is_refused(collector: ModuleType, tmp_path: Path) -> None:
    results = tmp_path / "results"
    shutil.copytree(collector.RESULTS_DIR, results)
    text = (results / "sim.md").read_text()
    (results / "sim.md").write_text(
        text.replace("- date: ", "- date: 2999-01-01 00:00 UTC; ", 1) + "| " + "x" * 320 + " |\n"
    )
    with pytest.raises(collector.ResultsError, match="over 300 characters"):
        collector.collect(results)


def test_an_old_measurement_states_no_figure(collector: ModuleType) -> None:
    text = collector.collect()
    for section in collector.SECTIONS:
        body = text.split(f'<a id="{section.key}"></a>')[1].split("<a id=")[0]
        dates = {
            name: collector.measured((collector.RESULTS_DIR / name).read_text()).date
            for name in section.files
            if name.endswith(".md")
        }
        for name, date in dates.items():
            old_line = f"`{name}`: measured {date} on older code"
            assert (old_line in body) == (date < collector.RESTATED_SINCE), (section.key, name)
        if all(date < collector.RESTATED_SINCE for date in dates.values()):
            assert "|---" not in body, section.key  # none of its tables


def test_readme_figures_link_to_a_results_section_and_every_doc_link_resolves(collector: ModuleType) -> None:
    repo = BENCHMARKS.parent
    readme = (repo / "README.md").read_text()
    headline = readme.split("## Headline figures")[1].split("\n## ")[0]
    rows = [line for line in headline.splitlines() if line.startswith("| ") and not line.startswith("| what")]
    anchors = {s.key for s in collector.SECTIONS}
    assert 0 < len(rows) <= 12
    for row in rows:
        links = re.findall(r"\(benchmarks/RESULTS\.md#([a-z_0-9]+)\)", row)
        assert links and set(links) <= anchors, row
    docs = [repo / "README.md", *sorted((repo / "docs").glob("*.md")), repo / "experiments" / "NOTEBOOK.md"]
    docs += [BENCHMARKS / "results" / "targets.md"]
    for doc in docs:
        for link in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
            path, _, anchor = link.partition("#")
            if link.startswith("http") or not path:
                continue
            target = (doc.parent / path).resolve()
            assert target.exists(), f"{doc.name}: {link}"
            if anchor and target.name == "RESULTS.md":
                assert anchor in anchors, f"{doc.name}: {link}"


def test_a_restated_result_without_its_json_is_refused(collector: ModuleType, tmp_path: Path) -> None:
    results = tmp_path / "results"
    shutil.copytree(collector.RESULTS_DIR, results)
    (results / "poses.json").unlink()
    with pytest.raises(collector.ResultsError, match="poses.md is restated but has no poses.json"):
        collector.check_raw(results)
    collector.check_raw(collector.RESULTS_DIR)  # the committed results: every restated file has its JSON or a reason
    for name in collector.RAW_MISSING:
        assert not (collector.RESULTS_DIR / name.replace(".md", ".json")).exists(), name


# JSON with no "measured" entry: vista and eval_startup were written before their scripts wrote through
# benchmarks/_lib/report.py (a new measurement brings it); threads_busy's script writes its own (date, machine on top).
WITHOUT_MEASURED = {"vista.json", "eval_startup.json", "threads_busy.json"}


def test_each_json_holds_when_where_and_at_what_load(collector: ModuleType) -> None:
    import json

    for section in collector.SECTIONS:
        for name in section.files:
            md = collector.RESULTS_DIR / name.replace(".json", ".md")
            if not name.endswith(".json") or not collector.restated(collector.measured(md.read_text())):
                continue
            data = json.loads((collector.RESULTS_DIR / name).read_text())
            if name in WITHOUT_MEASURED:
                continue
            measured = data.get("measured") or {}
            assert measured.get("date_utc", "").startswith(collector.measured(md.read_text()).date), name
            assert "CPU" in measured.get("machine", "") or "GPU" in measured.get("machine", ""), name
            assert measured.get("load_average_1_5_15_min") or measured.get("load_note"), name

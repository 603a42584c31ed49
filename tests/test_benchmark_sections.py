"""Every comparison writes its own section of its pages and leaves the others."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"



PAGE = """# Benchmarks

Header text.

<!-- bench_a:start -->
## A
old table of a
<!-- bench_a:end -->

<!-- bench_b:start -->
## B
table of b
<!-- bench_b:end -->
"""


def test_a_section_replaces_only_its_own_text(timing):
    page = timing.replace_section(PAGE, "bench_a", "## A\nnew table of a")
    assert "new table of a" in page and "old table of a" not in page
    start, end = timing.markers("bench_b")
    assert page.split(start)[1].split(end)[0] == PAGE.split(start)[1].split(end)[0]
    assert page.split("<!-- bench_a:start -->")[0] == PAGE.split("<!-- bench_a:start -->")[0]
    assert timing.replace_section(page, "bench_a", "## A\nold table of a") == PAGE


def test_a_new_section_is_appended_after_the_others(timing):
    page = timing.replace_section(PAGE, "bench_c", "## C\ntable of c")
    assert page.startswith(PAGE.rstrip("\n"))
    assert page.rstrip().endswith("<!-- bench_c:end -->")
    assert timing.replace_section(page, "bench_c", "## C\ntable of c") == page


def test_an_unclosed_section_is_refused(timing):
    with pytest.raises(ValueError, match="bench_a"):
        timing.replace_section("<!-- bench_a:start -->\nno end", "bench_a", "x")


def test_write_section_writes_the_command_and_the_table(timing, tmp_path, monkeypatch):
    page = tmp_path / "benchmarks.md"
    page.write_text(PAGE)
    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_b.py", "--turns", "2"])
    table = timing.markdown_table(("what", "ms"), [("step", "1.5")])
    timing.write_section("bench_b", "B", table, page)
    text = page.read_text()
    assert "`OMP_NUM_THREADS=1 python benchmarks/bench_b.py --turns 2`" in text
    assert "| what | ms |\n|---|---|\n| step | 1.5 |" in text
    assert "old table of a" in text and "table of b" not in text


def test_every_comparison_has_its_section_on_its_pages(timing):
    """The GPU check's comparisons only once a GPU machine has run them (``gpu_check.sh``); a
    comparison marked ``unmeasured`` has none until its first run, which removes the mark."""
    gpu_check = (BENCHMARKS / "gpu_check.sh").read_text()
    for name, spec in timing.workloads().items():
        for page_name in spec["pages"]:
            text = (BENCHMARKS.parent / "docs" / page_name).read_text()
            written = all(marker in text for marker in timing.markers(name))
            if spec.get("unmeasured"):
                assert not any(marker in text for marker in timing.markers(name)), \
                    (name, page_name, "has its section: drop its unmeasured mark")
            else:
                assert written or re.search(rf"\b{name}\b", gpu_check), (name, page_name)


def test_every_section_of_the_page_records_a_command_of_an_existing_comparison(timing):
    """It names a comparison of ``workloads.yaml`` that ``python -m benchmarks.timing`` runs, or
    a script that exists."""
    page = (BENCHMARKS.parent / "docs" / "benchmarks.md").read_text()
    names = re.findall(r"<!-- (\w+):start -->", page)
    assert len(names) >= 6
    for name in names:
        start, end = timing.markers(name)
        body = page.split(start)[1].split(end)[0]
        command = re.search(r"^`([^`]+)`, run on \d{4}-\d\d-\d\d \(", body, re.MULTILINE)
        assert command, name
        scripts = re.findall(r"(?:benchmarks|studies)/\w+\.(?:py|sh)", command.group(1))
        entries = re.findall(r"-m benchmarks\.timing (\w+)", command.group(1))
        assert scripts or entries, name
        assert all((BENCHMARKS.parent / s).is_file() for s in scripts), name
        assert all(entry in timing.workloads() for entry in entries), name


def test_benchmarks_import_only_the_harness():
    """One harness: a file of benchmarks/ imports ``timing`` and no other, so there is no circle
    (nor a second timing or table path hidden in a script)."""
    import ast

    scripts = {path.stem for path in BENCHMARKS.glob("*.py")}
    for path in sorted(BENCHMARKS.glob("*.py")):
        imported = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module:
                imported.add(node.module.split(".")[0])
        local = imported & scripts
        assert local <= ({"timing"} if path.stem != "timing" else set()), (path.name, local)


def test_the_curvature_profile_splits_a_product_into_its_operators():
    """``profile_iteration.py --curvature`` at a tiny size: the median product, the matrix
    products' share and the operator table; a leader without curvature products is one line."""
    import subprocess

    script = [sys.executable, str(BENCHMARKS / "profile_iteration.py"), "--iterations", "1",
              "--warmup", "1", "--lines", "5"]
    tiny = ["trainer.meta_batch=2", "benchmark.collector.episodes=2",
            "benchmark.collector.max_steps=5"]
    out = subprocess.run([*script, "--benchmark", "point_nav", "--method", "maml",
                          "--curvature", *tiny], capture_output=True, text=True, check=True)
    share = re.search(r"median KL curvature product [\d.]+ ms on a 2×2×5 meta-batch "
                      r".*; matrix products (\d+) % of the operators' own time", out.stdout)
    assert share and 0 < int(share.group(1)) < 100, out.stdout
    assert "aten::bmm" in out.stdout
    refused = subprocess.run([*script, "--benchmark", "sinusoid_uniform", "--method", "maml",
                              "--curvature"], capture_output=True, text=True)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines()[-1].endswith(
        "--curvature needs a MAML-TRPO leader; sinusoid_uniform has MAMLLeader")

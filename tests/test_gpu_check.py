"""The GPU check (``benchmarks/gpu_check.sh``) on any machine: its comparisons (``gpu_meta`` and
``gpu_warp`` in ``benchmarks/workloads.yaml``) at tiny size. Without CUDA the CUDA rows say so
instead of failing; with ``--cuda-as cpu`` every row runs, the MuJoCo Warp families on warp's CPU
device."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]



def table_rows(body: str) -> dict[tuple[str, str], list[str]]:
    """The table's rows by (benchmark, row label): their remaining cells."""
    rows = [line.strip("|").split(" | ") for line in body.splitlines() if line.startswith("| ")]
    return {(cells[0].strip(), cells[1]): [c.strip() for c in cells[2:]] for cells in rows[1:]}


def expected(timing, name: str, compiled: bool) -> set[tuple[str, str]]:
    """Every row of comparison ``name`` as the tiny table shows it."""
    return {(timing.group_label(group, tiny=True), label)
            for group in timing.workloads()[name]["groups"] for label, row in group["rows"].items()
            if compiled or "compile=true" not in str(row)}


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks what a machine without CUDA does")
def test_without_cuda_the_cuda_rows_say_so_and_the_others_run(timing):
    body = timing.compare_in_turns("gpu_meta", ["--tiny", "--no-doc"])
    rows = table_rows(body)
    assert set(rows) == expected(timing, "gpu_meta", compiled=True)
    for (_, label), cells in rows.items():
        if label.startswith("cuda"):
            assert cells[-1] == "skipped: no CUDA", (label, cells)
        else:
            assert float(cells[0]) > 0 and cells[-1] == "–", (label, cells)


@pytest.mark.skipif(importlib.util.find_spec("mujoco_warp") is None,
                    reason="the MuJoCo Warp rows need mujoco-warp (the gpu extra)")
@pytest.mark.parametrize("name", ["gpu_meta", "gpu_warp"])
def test_every_row_of_the_check_runs_in_place_of_cuda(timing, name):
    body = timing.compare_in_turns(name, ["--tiny", "--cuda-as", "cpu", "--no-compile",
                                          "--no-doc"])
    rows = table_rows(body)
    assert set(rows) == expected(timing, name, compiled=False)
    assert all(float(cells[0]) > 0 for cells in rows.values()), rows


def test_the_check_runs_both_comparisons_and_test_files_that_exist(timing):
    script = (ROOT / "benchmarks" / "gpu_check.sh").read_text()
    entries = re.search(r"for entry in ([\w ]+); do", script).group(1).split()
    assert entries == ["gpu_meta", "gpu_warp"]
    assert all(name in timing.workloads() for name in entries)
    tests = re.findall(r"tests/\w+\.py", script)
    assert tests and all((ROOT / path).is_file() for path in tests)


def test_a_row_that_fails_to_build_is_one_line_and_the_others_run(timing, tmp_path, monkeypatch):
    workloads = tmp_path / "workloads.yaml"
    workloads.write_text(
        "broken:\n  title: t\n  about: a\n  pages: []\n  rounds: 1\n  calls: 1\n  warmup: 1\n"
        "  base: [method=maml, trainer.meta_batch=2]\n  groups:\n"
        "    - {benchmark: sinusoid_uniform, rows: {fine: [], wrong: [trainer.no_such_key=1]}}\n")
    monkeypatch.setattr(timing, "WORKLOADS", workloads)
    rows = table_rows(timing.compare_in_turns("broken", ["--no-doc"]))
    assert float(rows[("sinusoid_uniform", "fine")][0]) > 0
    assert rows[("sinusoid_uniform", "wrong")][-1].startswith("error: ConfigCompositionException")
    assert "To append" in rows[("sinusoid_uniform", "wrong")][-1]  # the whole message, one line

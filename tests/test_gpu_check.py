"""The GPU check's dry run (``benchmarks/gpu_check.py run --dry-run``): every workload line under
``gpu_check`` in ``benchmarks/workloads.yaml`` at tiny size in one process, on a machine with or
without CUDA. The section it writes names the machine and has a row for every check; without CUDA
the CUDA rows say so instead of failing, and the MuJoCo Warp lines run on warp's CPU device where
it has one."""

from __future__ import annotations

import importlib
import importlib.util
import os
import platform
from pathlib import Path

import torch
import yaml

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_a_dry_run_writes_a_row_for_every_check_and_names_the_machine(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    gpu_check = importlib.import_module("gpu_check")
    warp_cpu = importlib.util.find_spec("mujoco_warp") is not None
    page = tmp_path / "benchmarks.md"
    page.write_text("# Benchmarks\n\n<!-- other:start -->\nkept\n<!-- other:end -->\n")
    gpu_check.main(["run", "--dry-run", "--out", str(tmp_path / "out"), "--page", str(page),
                    "--warp-device", "cpu" if warp_cpu else "cuda",
                    "--command-line", "benchmarks/gpu_check.sh --dry-run"])
    text = page.read_text()
    assert "<!-- other:start -->\nkept\n<!-- other:end -->" in text
    section = text.split("<!-- gpu_check:start -->")[1].split("<!-- gpu_check:end -->")[0]
    assert f"({platform.machine()}, {os.cpu_count()} logical CPUs, torch {torch.__version__}" \
        in section
    assert "`benchmarks/gpu_check.sh --dry-run`, run on" in section
    assert "Machine: " + ("no GPU" if not torch.cuda.is_available() else "") in section
    assert "| error" not in section and "error:" not in section
    cuda = "| ok |" if torch.cuda.is_available() else "skipped: no CUDA |"
    spec = yaml.safe_load((BENCHMARKS / "workloads.yaml").read_text())["gpu_check"]
    for path in spec["tests"]:
        assert f"| {Path(path).stem} | skipped: dry run |" in section
    for line in spec["meta"]:
        cpu_row = f"| {line['benchmark']} | {line['method']} | cpu | eager | "
        assert cpu_row in section and f"{cpu_row}– |" not in section, line
        rows = [row for row in section.splitlines()
                if row.startswith(f"| {line['benchmark']} | {line['method']} | cuda |")]
        variants = 1 + bool(line.get("no_graphs")) + bool(line.get("compiled"))
        assert len(rows) == variants, line
        assert torch.cuda.is_available() or all(row.endswith(cuda) for row in rows), rows
    for line in spec["warp"]:
        for part in gpu_check.WARP_PARTS:
            row = next(row for row in section.splitlines()
                       if row.startswith(f"| {line['benchmark']} | {part} |"))
            assert ("skipped" not in row) if warp_cpu else row.endswith(cuda), row
        if "target_steps_per_s" in line:
            assert f"{line['benchmark']} >= {line['target_steps_per_s']:,} env steps/s: " in section
    assert "not the target's size" in section or not warp_cpu
    for part in ("preflight", "meta-point_nav", "compiled-sinusoid_uniform"):
        assert f"| {part} | ok |" in section
    assert (tmp_path / "out" / "summary.txt").read_text().startswith("gpu_check ")

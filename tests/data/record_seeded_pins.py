"""Record ``seeded_pins.json``: each benchmark family's seeded run, and how far rounding moves it.

The reference values come from this machine's default kernels. The same runs are then repeated
under other kernels of this machine: torch's CPU capabilities (``ATEN_CPU_CAPABILITY``) and MKL's
code paths (``MKL_CBWR``). Each pinned number gets a tolerance of ``SAFETY`` times the largest
move any of those variants made, and at least ``FLOOR`` relative. The file being replaced holds
another machine's numbers: a number recorded there too keeps at least its tolerance there and
gets at least ``MACHINES`` times its move between the two machines, and a number new to the file
(one whose meaning changed) at least ``MACHINES`` times the largest relative move of its
family's other numbers. CPUs whose kernels
round differently again move the numbers by about the same order, while a change of the random
streams or of the maths moves them by far more.

Run it from the repository root, on one thread, only for a change meant to alter seeded numbers
(``--changed KEY ...``: the kept numbers whose meaning the change altered, which the file being
replaced cannot vouch for):

    OMP_NUM_THREADS=1 python tests/data/record_seeded_pins.py --changed adversarial.kl_p0
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

SAFETY = 10.0
FLOOR = 1e-3
MACHINES = 3.0
KEPT = ("initial.mean", "initial.cvar.0.5", "adversarial.mean", "adversarial.cvar.0.5",
        "adversarial.kl_p0")
VARIANTS = ({"ATEN_CPU_CAPABILITY": "default"}, {"ATEN_CPU_CAPABILITY": "avx2"},
            {"MKL_CBWR": "COMPATIBLE"}, {"MKL_CBWR": "AVX2"})
OUT = Path(__file__).with_name("seeded_pins.json")
TESTS = Path(__file__).resolve().parents[1]


def seeded_values() -> dict[str, dict[str, float]]:
    """Every family's kept numbers, run in this process."""
    import torch

    sys.path.insert(0, str(TESTS))
    from test_seeded_pins import COMMON, RUNS, flatten

    from armeta_rl.config import validate
    from armeta_rl.job import Job
    from armeta_rl.trainers.training import run_training
    from conftest import compose_train

    torch.set_num_threads(1)
    values = {}
    for benchmark, overrides in RUNS.items():
        with tempfile.TemporaryDirectory() as run_dir:
            cfg = compose_train(*COMMON, f"benchmark={benchmark}", *overrides)
            flat = flatten(run_training(Job(validate(cfg), run_dir), progress=False))
        values[benchmark] = {key: flat[key] for key in KEPT}
    return values


def in_subprocess(environment: dict[str, str]) -> dict[str, dict[str, float]]:
    result = subprocess.run([sys.executable, __file__, "--values"], capture_output=True,
                            text=True, check=True, env={**os.environ, **environment})
    return json.loads(result.stdout.strip().splitlines()[-1])


def machine_moves(reference: dict[str, dict[str, float]], previous: dict[str, dict],
                  changed: set[str]) -> dict[str, dict[str, float]]:
    """Per family and number, the least tolerance the other machine's numbers (the file being
    replaced, ``previous``) ask for: their tolerance there and ``MACHINES`` times the move
    between the two machines, and for a number in ``changed`` (or absent there) ``MACHINES``
    times the family's largest relative move applied to its value."""
    least = {}
    for family, numbers in reference.items():
        pinned = previous.get(family, {})
        kept = [key for key in numbers if key in pinned and key not in changed]
        moves = {key: abs(numbers[key] - pinned[key]["value"]) for key in kept}
        relative = max((moves[key] / abs(numbers[key]) for key in kept if numbers[key]),
                       default=0.0)
        least[family] = {key: max(MACHINES * moves[key], pinned[key]["tolerance"])
                         if key in moves else MACHINES * relative * abs(value)
                         for key, value in numbers.items()}
    return least


def main(changed: set[str]) -> None:
    previous = json.loads(OUT.read_text())["pins"] if OUT.is_file() else {}
    reference = in_subprocess({})
    moved = {family: dict.fromkeys(numbers, 0.0) for family, numbers in reference.items()}
    for environment in VARIANTS:
        for family, numbers in in_subprocess(environment).items():
            for key, value in numbers.items():
                moved[family][key] = max(moved[family][key], abs(value - reference[family][key]))
    least = machine_moves(reference, previous, changed)
    pins = {family: {key: {"value": value,
                           "tolerance": max(SAFETY * moved[family][key], FLOOR * abs(value),
                                            least[family][key])}
                     for key, value in numbers.items()}
            for family, numbers in reference.items()}
    OUT.write_text(json.dumps({"variants": list(VARIANTS), "safety": SAFETY, "floor": FLOOR,
                               "machines": MACHINES, "pins": pins}, indent=1) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    if sys.argv[1:] == ["--values"]:
        print(json.dumps(seeded_values()))
    else:
        parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
        parser.add_argument("--changed", nargs="*", default=[], choices=KEPT,
                            help="kept numbers whose meaning the change altered")
        main(set(parser.parse_args().changed))

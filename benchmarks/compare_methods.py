"""Score every run of a sweep on p0 and on one saved adversary, and print a Markdown table.

    armeta-train -m method=maml,dr_maml,tr_maml,dro_maml,ar_maml,cnp,dr_cnp,tr_cnp,dro_cnp,ar_cnp \\
        trainer.iterations=3000 seed=0 hydra.sweep.dir=runs/compare
    python benchmarks/compare_methods.py runs/compare runs/compare/4_sinusoid_uniform_ar_maml_seed0

Every method is evaluated on the same tasks (the eval seed of each run's config) from the initial
distribution and from the adversary saved in the second directory, so the columns compare.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from armeta_rl.allocator import keep_freed_memory
from armeta_rl.config import CONFIG_FILE
from armeta_rl.trainers.run import cross_evaluate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("sweep", type=Path, help="directory holding one run directory per method")
    parser.add_argument("adversary", type=Path, help="run directory of the adversary to score on")
    parser.add_argument("--alpha", default="0.5", help="CVaR level to show (one of eval.alphas)")
    args = parser.parse_args()
    keep_freed_memory()
    torch.set_num_threads(1)
    runs = sorted(p.parent for p in args.sweep.glob(f"*/{CONFIG_FILE}"))
    print(f"adversary: {args.adversary}")
    print(f"| method | initial mean | initial CVaR{args.alpha} | adversarial mean "
          f"| adversarial CVaR{args.alpha} |")
    print("|---|---|---|---|---|")
    for run in runs:
        report = cross_evaluate(run, args.adversary)
        initial, shifted = report["initial"], report["adversarial"]
        print(f"| {report['method']} | {initial['mean']:.3f} | {initial['cvar'][args.alpha]:.3f} "
              f"| {shifted['mean']:.3f} | {shifted['cvar'][args.alpha]:.3f} |")


if __name__ == "__main__":
    main()

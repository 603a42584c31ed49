"""Reproducing the paper: each table or figure is an experiment declared in
``configs/reproduce/<experiment>.yaml``, run as Hydra multiruns of ``armeta-train`` and
``armeta-eval`` and aggregated into CSV, Markdown and PNG (``armeta-reproduce``,
docs/reproducing.md).
"""

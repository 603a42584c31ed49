"""A Hydra sweeper that launches an explicit list of jobs (``armeta-reproduce``'s sweeps)."""

"""armeta_rl.envs."""

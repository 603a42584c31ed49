"""armeta_rl.rl."""

"""armeta_rl.risk."""

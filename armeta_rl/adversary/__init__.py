"""armeta_rl.adversary."""

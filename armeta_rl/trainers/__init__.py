"""armeta_rl.trainers."""

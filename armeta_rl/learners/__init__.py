"""armeta_rl.learners."""

"""The sim-to-real diagnosis: the rounds of candidate refits, misfit location and features,
held-out folds, regime screen and profile."""

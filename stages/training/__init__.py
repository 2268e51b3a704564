"""Layer ``training``: one optimisation run (state, step, checkpoints, loss records). Above
``guidance`` (its objective) and ``imaging`` (the images it builds per step)."""

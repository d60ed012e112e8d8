"""Reading and writing scenes and runs: checkpoints, PLY."""

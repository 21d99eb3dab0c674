"""The inverse-rendering job: preparation, losses, the alternating loop of Sec. 5, checkpoints."""

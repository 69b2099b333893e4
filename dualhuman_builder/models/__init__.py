"""Trainers that consume the exported dataset: the reaction prior (motion VAE + invertible network)
and the two-person pose estimator of the Dual-Human paper, with their metrics. Holds no code yet."""

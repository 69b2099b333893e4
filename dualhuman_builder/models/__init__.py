"""Trainers that consume the exported dataset: the reaction prior (motion VAE + invertible network)
and the two-person pose estimator of the Dual-Human paper, with their metrics. Each model registers itself
(:func:`~dualhuman_builder.models.base.get_model` imports them on first use)."""

"""The reaction prior of the Dual-Human paper (§3.1, §3.4-3.5): a motion VAE, an invertible network
from the actor's latent distribution to the reactor's, and test-time refinement of a noisy reactor.

Modules: :mod:`.representation` (both people's joints in the actor's window frame, normalisation),
:mod:`.vae` (the Transformer VAE; the DCT code of the no-VAE ablation), :mod:`.inn` (the affine
coupling network; the MLP of the ablation), :mod:`.noise` (visibility-driven corruption),
:mod:`.spec` (the model spec: phases ``vae`` then ``inn``, losses, evaluation), :mod:`.refine`
(test-time optimisation and :func:`~.refine.refine_export`).
"""

from dualhuman_builder.models.base import register
from dualhuman_builder.models.reaction_prior.spec import NAME, ReactionPrior, ReactionPriorSpec

register(NAME, ReactionPriorSpec)

__all__ = ["NAME", "ReactionPrior", "ReactionPriorSpec"]

"""The two-person pose estimator of the Dual-Human paper (§3.2): from an image of two people in close
interaction, both people's 3-D joints, translations and saliency.

Modules: :mod:`.attention` (the queries and the intra- and inter-human attention masks),
:mod:`.network` (backbone, decoder, heads; :func:`~.network.to_camera`), :mod:`.losses` (smooth-L1 pose,
L2 translation, cross-entropy saliency, Hungarian matching), :mod:`.spec` (the model spec, phase
``estimator``; :func:`~.spec.predict`).
"""

from dualhuman_builder.models.base import register
from dualhuman_builder.models.pose_estimator.network import PoseEstimator, to_camera
from dualhuman_builder.models.pose_estimator.spec import NAME, PoseEstimatorSpec, predict

register(NAME, PoseEstimatorSpec)

__all__ = ["NAME", "PoseEstimator", "PoseEstimatorSpec", "predict", "to_camera"]

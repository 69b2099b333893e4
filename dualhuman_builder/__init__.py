"""dualhuman_builder: build datasets of two people in close interaction.

Stages, one subpackage each, in data-flow order: ``capture`` (device sources, take files,
recording, replay, importers), ``sync`` (clocks, lags, tracker mounts), ``fit`` (fusion, shape
calibration, joint two-person fitting), ``contacts`` (per-vertex contacts), ``render`` (Mitsuba
multi-view images), ``export`` (dataset layout, features, loaders); ``models`` is reserved for
trainers that consume the dataset. ``pipeline`` lists the workspace stages in order.

Foundations: ``conventions`` (units and frames), ``tracks`` (core data types), ``body`` (the anny
body model), ``geometry`` (distance and collision kernels), ``rig``, ``labels``, ``fileio``,
``errors``, ``workspace`` (catalog and stage runner). Beside the stages: ``sim`` (ground-truth
scenes and simulated devices) and ``evaluation`` (scores against that ground truth).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dualhuman-builder")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0.0.0+unknown"

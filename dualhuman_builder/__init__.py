"""dualhuman_builder: build datasets of two people in close interaction.

Stages, one subpackage each, in data-flow order: ``capture`` (device adapters, recording,
replay), ``sync`` (clock alignment), ``fit`` (fusion, shape calibration, joint two-person fitting),
``contacts`` (libigl vertex contacts), ``render`` (Mitsuba multi-view images), ``export`` (dataset
layout, features, loaders), ``models`` (trainers that consume the dataset). Shared pieces:
``body`` (the anny body model), ``tracks`` (core data types), ``workspace`` (catalog and stage
runner), ``conventions`` (units and frames).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dualhuman-builder")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0.0.0+unknown"

"""Fuse, calibrate and fit stages: from synced streams to two interacting bodies.

Fusion makes one drift-free :class:`~dualhuman_builder.tracks.SkeletonTrack` per actor (suit
orientations, tracker-corrected positions); calibration solves one anny shape per actor per take;
fitting retargets segment orientations onto anny bones through ``rigs/mvn_anny.toml`` and refines
both actors jointly over windows of frames with an SDF collision term. Arrives with the fitting
issue; :mod:`dualhuman_builder.body` already provides the model, the mapping and the T-pose.
"""

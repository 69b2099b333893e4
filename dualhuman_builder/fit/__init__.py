"""Fuse, calibrate and fit stages: from synced streams to two interacting bodies.

Fusion makes one drift-free :class:`~dualhuman_builder.tracks.SkeletonTrack` per actor (suit
orientations, tracker-corrected positions; :mod:`.fuse`); calibration solves one anny shape per actor
per take (:mod:`.calibrate`); fitting retargets segment orientations onto anny bones through
``rigs/mvn_anny.toml`` and refines both actors jointly over windows of frames with an SDF collision
term (:mod:`.fitter`, the entry point; its parts: :mod:`.config`, :mod:`.inputs`, :mod:`.actors`,
:mod:`.energy`, :mod:`.problem`, :mod:`.segment`, :mod:`.collision_rounds`, :mod:`.layout`,
:mod:`.seams`, :mod:`.workers`; the whole take as one problem instead: :mod:`.take`, its batched
per-block L-BFGS :mod:`.block_lbfgs`). :mod:`.process` runs the whole path on a take in memory;
:mod:`.stage` runs it as workspace stages; :mod:`.report` draws the fit's report.
"""

"""Contacts stage: per-vertex contact labels between the two fitted meshes with libigl.

Signed distances of each body's vertices to the other's mesh (``igl.signed_distance`` with a
distance band), per-vertex labels, per-frame flags and region-level events over the regions of
``rigs/anny_regions.toml``. The mesh is watertight (see :mod:`dualhuman_builder.body.topology`),
so pseudonormal signs are exact on the body component. Arrives with the contacts issue.
"""

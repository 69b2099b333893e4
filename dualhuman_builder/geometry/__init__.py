"""Geometry kernels shared by the fit, the contacts and the scene checks; they import no stage.

* :mod:`.collision` — the differentiable collision term between two bodies (the fit's penetration
  term, also the scene generator's winding-number penetration check), a package;
* :mod:`.distance` — signed distances between two deforming body meshes (warp BVH queries, float32);
* :mod:`.narrow` — the contacts stage's narrow phase: the vertices near the other mesh and the
  faces libigl needs for them;
* :mod:`.pseudonormal` — signed distance to a known closest face with libigl's sign rule (float64).

Positions are metres in the world frame of :mod:`dualhuman_builder.conventions`; meshes are anny's
topology, queried against its closed body component
(:func:`~dualhuman_builder.body.topology.collision_faces`).
"""

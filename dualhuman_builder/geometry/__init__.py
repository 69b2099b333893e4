"""Geometry kernels shared by the fit, the contacts and the scene checks.

* :mod:`.collision` — the differentiable collision term between two bodies (the fit's SDF term,
  also the scene generator's penetration check);
* :mod:`.distance` — signed distances between two deforming body meshes (warp BVH queries);
* :mod:`.narrow` and :mod:`.pseudonormal` — the narrow band of vertices near the other mesh, and
  signed distance to a known closest face with libigl's sign rule.
"""

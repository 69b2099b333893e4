"""Evaluation against ground truth: what a stage's output is worth on a simulated take whose every
joint, vertex and contact is known.

* :mod:`.fit` — the whole path (simulated devices -> capture -> sync -> fuse -> fit) scored against
  the scene: joint and root error, penetration, clocks, mounts, foot slide;
* :mod:`.contacts` — contacts of a scene's bodies against its own per-vertex contacts, and the fitted
  pair's contacts against the ground truth's (per-vertex precision, recall and F1 per take and body
  region; contact-event onset and offset errors).
"""

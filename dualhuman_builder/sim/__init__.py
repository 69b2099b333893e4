"""Ground truth and simulated devices.

* two-person scenes whose every vertex and contact is known: :mod:`.scenes` (built with
  :mod:`.performer`, :mod:`.ik`, :mod:`.skeleton`, :mod:`.timeline`; checked by :mod:`.quality`);
* simulators that turn a scene into the noisy, drifting, clock-skewed streams a real studio
  produces: :mod:`.suit`, :mod:`.trackers`, :mod:`.imu` (over :mod:`.kinematics` and
  :mod:`.groundtruth`), all of one studio in :mod:`.studio`;
* players that put those streams on real transports in the real wire formats: :mod:`.devices`,
  :mod:`.play`, :mod:`.loopback`; the ``sim://`` source (:mod:`.source`); recorded-file writers
  (:mod:`.files`); the ``scene`` and ``devices`` workspace stages (:mod:`.stage`).

Downstream stages are scored against this ground truth by :mod:`dualhuman_builder.evaluation`.
"""

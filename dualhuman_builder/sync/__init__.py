"""Sync stage: clock alignment of a take's streams.

Per stream, the offset and drift between its device clock and the host clock (a robust line fit
over device-vs-host timestamps, :mod:`.clock`); between each tracker and the suit segment it is
strapped to, the residual lag by cross-correlating speed magnitudes (:mod:`.lag`) and the
mounting rotation and offset by least squares (:mod:`.mount`, with its parts :mod:`.mount_types`,
:mod:`.mount_rotation`, :mod:`.mount_translation`, :mod:`.mount_constellation` and :mod:`.knots`);
then every stream resampled to one timeline (:mod:`.timeline`, :mod:`.resample`). The workspace
stage: :mod:`.stage`.
"""

from dualhuman_builder.sync.clock import ClockFit, fit_clock, relative_clock
from dualhuman_builder.sync.lag import LagEstimate, angular_speed, combine_lags, estimate_lag
from dualhuman_builder.sync.mount import MountCalibration, calibrate_mounts
from dualhuman_builder.sync.timeline import ActorStreams, SyncError, SyncResult, synchronise

__all__ = ["ClockFit", "fit_clock", "relative_clock", "LagEstimate", "angular_speed", "combine_lags", "estimate_lag",
           "MountCalibration", "calibrate_mounts", "ActorStreams", "SyncError", "SyncResult", "synchronise"]

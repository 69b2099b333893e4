"""Sync stage: clock alignment of a take's streams.

Per stream, the offset and drift between its device clock and the host clock (a robust line fit
over device-vs-host timestamps); between each tracker and the suit segment it is strapped to, the
residual lag by cross-correlating angular-velocity magnitudes and the mounting rotation by least
squares; then every stream resampled to one timeline. Arrives with the fitting issue.
"""

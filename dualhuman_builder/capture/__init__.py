"""Capture stage: device adapters that turn live streams and recorded files into typed samples.

Sources are named by URL, one handler per scheme (as pyserial names ports):
``mvn+udp://0.0.0.0:9763`` (Xsens MVN network stream), ``xbus:///dev/ttyUSB0?baud=921600`` (MTi
over serial), ``mti+can://virtual/0`` (MTi-600 over CAN), ``vive+udp://:8051`` (VIVE bridge),
``vive+usb://`` (VIVE tracker HID) and ``sim://handshake?seed=3`` (simulated devices that speak
the real wire formats). Every sample keeps the device timestamp and the host's monotonic receive
time in nanoseconds.

* :mod:`.sources` — the Source / Decoder interface and the scheme registry; one module per
  device family (:mod:`.mvn_udp`, :mod:`.vive_udp`, :mod:`.xbus_serial`, :mod:`.mti_can`,
  :mod:`.vive_usb`; ``sim://`` is registered by :mod:`dualhuman_builder.sim.source` through an
  entry point), wire formats in :mod:`.wire`;
* :mod:`.recorder` and :mod:`.recording` — recording takes (live status, clean stops);
  :mod:`.log` — take files (MCAP): writing, reading, check, repair, dump;
* :mod:`.replay` — samples back to the pipeline, or raw packets back onto the wire;
* :mod:`.importers` — MVNX and BVH files;
* :mod:`.backends` — which transports can open on this machine (used by ``dualhuman doctor``).
"""

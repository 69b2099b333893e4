"""Capture stage: device adapters that turn live streams and recorded files into typed samples.

Sources are named by URL, one handler per scheme (as pyserial names ports):
``mvn+udp://0.0.0.0:9763`` (Xsens MVN network stream), ``xbus:///dev/ttyUSB0?baud=921600`` (MTi
over serial), ``mti+can://virtual/0`` (MTi-600 over CAN), ``vive+udp://:8051`` (VIVE bridge),
``vive+usb://`` (VIVE tracker HID) and ``sim://handshake?seed=3`` (simulated devices that speak
the real wire formats). Every sample keeps the device timestamp and the host's monotonic receive
time in nanoseconds. The adapters, recording and replay come with a later issue;
:mod:`.backends` already probes which transports can open on this machine.
"""

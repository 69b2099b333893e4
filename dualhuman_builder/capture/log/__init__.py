"""Take files: one MCAP file per take (:mod:`.writer`), read back tolerant of damage (:mod:`.reader`),
with the typed samples stored as self-describing ROS 1 messages (:mod:`.schemas`)."""

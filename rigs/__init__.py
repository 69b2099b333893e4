"""The toolkit's bundled rigs, segment mapping and body-part regions (package data
``dualhuman_builder.rigs``; see :mod:`dualhuman_builder.resources`)."""

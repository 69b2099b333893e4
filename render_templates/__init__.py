"""The toolkit's bundled render templates (package data ``dualhuman_builder.render_templates``;
see :mod:`dualhuman_builder.resources`)."""

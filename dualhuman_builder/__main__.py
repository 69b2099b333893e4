"""`python -m dualhuman_builder ...` is the `dualhuman` command."""

from dualhuman_builder.cli import main

main()

"""`python cli.py ...`: the `dualhuman` command from a checkout. The command tree lives in
:mod:`dualhuman_builder.cli`; the installed console script is ``dualhuman_builder.cli:main``."""

from dualhuman_builder.cli import main

if __name__ == "__main__":
    main()

"""Quality gates and the review page: above the stages, reading their artifacts and reports.

:mod:`.gates` checks a take's stage results against the thresholds of ``gates.toml`` and stores
the failures as flags in the catalog; :mod:`.review` writes a workspace's static HTML review page.
No stage imports this package (``pyproject.toml``'s import-linter contracts).
"""

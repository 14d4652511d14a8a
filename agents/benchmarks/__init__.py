"""``tensegrity-gym bench``: :mod:`~agents.benchmarks.suite` runs the benchmarks of the
other modules here and prints one JSON document. Nothing a user imports to train,
evaluate or record imports this package."""

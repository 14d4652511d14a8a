"""Evaluating policies under each estimator and harder sensing
(:mod:`~agents.evaluation.evaluate`), the sim-to-real report
(:mod:`~agents.evaluation.report`) and its plots (:mod:`~agents.evaluation.plots`)."""

"""Runs and bags: recording runs and estimating over bags offline
(:mod:`~agents.recordings.offline`), runs held in memory (:mod:`~agents.recordings.runs`),
UWB calibration files (:mod:`~agents.recordings.calibrate`) and the live view
(:mod:`~agents.recordings.view`)."""

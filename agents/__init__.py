"""What people run on top of the envs, one concern per sub-package:

- :mod:`agents.training`: training with stable-baselines3 (``train``), its configs, the
  hyperparameter ranges, the guards against divergence, and the Ray cluster.
- :mod:`agents.evaluation`: policies under each estimator (``evaluate``), the sim-to-real
  report and its plots.
- :mod:`agents.identification`: system identification from a bag (``identify``).
- :mod:`agents.recordings`: runs recorded to bags (``record``), estimators run over bags
  offline (``estimate``), UWB calibration (``calibrate``) and the live view (``view``).
- :mod:`agents.benchmarks`: ``tensegrity-gym bench``; nothing above imports it.
- :mod:`agents.gait`: the scripted gait command (``gait``); :mod:`agents.demo`: the
  demo (``demo``).
- :mod:`agents.cli`: the ``tensegrity-gym`` command line, thin definitions over the above.
"""

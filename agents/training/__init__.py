"""Training rolling policies with stable-baselines3: :mod:`~agents.training.train` (the
run), :mod:`~agents.training.hyperparams` (the valid values), :mod:`~agents.training.guards`
(no non-finite model is written), ``configs/`` (rl-zoo3's layout) and
:mod:`~agents.training.cluster` (a run's envs on a Ray cluster)."""

"""System identification from a recorded run: the fit
(:mod:`~agents.identification.identify`), its IMU term (:mod:`~agents.identification.imu`)
and the command with its report (:mod:`~agents.identification.report`)."""

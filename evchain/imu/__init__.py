"""Ground truth from a camera's gyro: the rotational motion field (:mod:`.rotflow`), gyro
samples as a function of time (:mod:`.gyro`), the calibration of principal point, time offset
and bias against measured normal flow (:mod:`.calibrate`) and the truth provider
(:mod:`.truth`) that the ``imu_truth`` stage sets as ``context.truth``."""

"""Sensor-side conversions shared by bridge, replay and hil.

* :mod:`imu.boards` — what a RAW_IMU message's integers mean on a given board (GY-86 raw
  register counts, ArduPilot's mG / mrad/s / mGauss), to SI in the body frame FRD;
* :mod:`imu.rotations` — sensor-to-body mounting rotations by their PX4/ArduPilot names;
* :mod:`imu.calibration` / :mod:`imu.calibration_fit` — per-sensor offset + matrix
  corrections and fitting them from recorded samples.

Nothing here does I/O on links or knows about asyncio; it sits below ``bridge``,
``replay`` and ``hil``, which all import it.
"""

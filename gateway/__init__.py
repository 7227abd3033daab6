"""The gateway: calibration and kinematics between raw samples and poses."""

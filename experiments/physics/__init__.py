"""The physics check and what is measured with it: agreement, correlation, the envelope, calibration."""

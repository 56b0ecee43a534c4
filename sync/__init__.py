"""Sync stage: IMU <-> Kinect clock offset and drift, resampling onto one timeline.
Filled in by the sync and fitting issue."""

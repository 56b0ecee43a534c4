"""Capture stage: raw hardware recordings (Azure Kinect MKV / frame folders, Xsens MVNX / Xbus)
into typed in-memory streams, camera calibration, point clouds. Filled in by the capture issue."""

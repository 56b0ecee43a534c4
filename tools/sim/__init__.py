"""The hardware simulator behind `couch-simulate`: procedural human-chair motion, parametric
chairs and a room, Azure-Kinect-like cameras and Xsens IMUs writing the real device formats,
and ground truth in the processed-session schema."""

"""Synthesis stage: ControlNet, PoseNet, ContactNet, `couch-train`, `couch-synthesize`.
Filled in by the synthesis issue."""

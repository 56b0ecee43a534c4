"""Tools: demo, rendering, benchmarks, the body-model generator; later the simulator, QA and
exporters."""

"""The in-process harness that runs the whole node graph (tests and the demo)."""

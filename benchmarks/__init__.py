"""Performance benchmarks of bcid_ros (run with ``python -m benchmarks.run``)."""

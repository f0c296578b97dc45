"""kimera-multi-py: multi-robot distributed metric-semantic SLAM over Eclipse Zenoh."""

__version__ = "0.1.0"

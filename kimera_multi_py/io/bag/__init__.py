"""ROS 1 and ROS 2 bags: a robot's keyframe source and a writer of standard messages (docs/bags.md)."""

from kimera_multi_py.io.bag.config import BagConfig, config_for, load_bag_config
from kimera_multi_py.io.bag.errors import BagError
from kimera_multi_py.io.bag.reader import BagSource
from kimera_multi_py.io.bag.writer import BagWriter

__all__ = ["BagConfig", "BagError", "BagSource", "BagWriter", "config_for", "load_bag_config"]

"""The semantic vocabulary shared by the simulator, the maps and the evaluation.

Class id 0 is ``free`` (the pivot of the log-odds vector); ids 1..K are semantic classes.
"""

from __future__ import annotations

import numpy as np

CLASS_NAMES: tuple[str, ...] = (
    "free",
    "wall",
    "floor",
    "ceiling",
    "door",
    "chair",
    "table",
    "sofa",
    "cabinet",
    "monitor",
    "plant",
    "bed",
    "human",
)
CLASS_IDS: dict[str, int] = {name: i for i, name in enumerate(CLASS_NAMES)}
NUM_CLASSES: int = len(CLASS_NAMES) - 1  # K, not counting free

STRUCTURE_CLASSES: frozenset[str] = frozenset({"wall", "floor", "ceiling"})
DYNAMIC_CLASSES: frozenset[str] = frozenset({"human"})
OBJECT_CLASSES: tuple[str, ...] = tuple(
    n for n in CLASS_NAMES[1:] if n not in STRUCTURE_CLASSES and n not in DYNAMIC_CLASSES
)

# Largest horizontal extent (m) an object of a class plausibly has: object-map merges that would
# exceed it are refused (two cabinets side by side are two cabinets, not one fused box).
MAX_OBJECT_EXTENT: dict[str, float] = {
    "door": 1.6, "chair": 1.4, "table": 3.8, "sofa": 3.0, "cabinet": 1.8, "monitor": 1.6,
    "plant": 1.5, "bed": 3.0,
}

# RGB colours (uint8) per class id, for PLY export and Rerun.
CLASS_COLORS: np.ndarray = np.array(
    [
        [255, 255, 255],  # free
        [170, 170, 170],  # wall
        [120, 90, 60],  # floor
        [220, 220, 200],  # ceiling
        [160, 82, 45],  # door
        [230, 25, 75],  # chair
        [60, 180, 75],  # table
        [255, 225, 25],  # sofa
        [0, 130, 200],  # cabinet
        [245, 130, 48],  # monitor
        [70, 240, 240],  # plant
        [240, 50, 230],  # bed
        [255, 0, 0],  # human
    ],
    dtype=np.uint8,
)


def class_id(name: str) -> int:
    """Id of a class name; ``KeyError`` names the unknown class."""
    try:
        return CLASS_IDS[name]
    except KeyError:
        raise KeyError(f"unknown class {name!r} (known: {', '.join(CLASS_NAMES[1:])})") from None

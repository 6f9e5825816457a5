"""mapserver: finds added and removed obstacles in robots' SLAM maps against the fleet's map.

The names below are imported on first use (PEP 562), not with the package: every ``mapserver``
command imports this package first, and most of them (``check-config``, ``bundle``, the daemon's
main process) never touch the image code or OpenCV.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mapserver.config import Config, load_config
    from mapserver.errors import (
        BundleError,
        BundleIncomplete,
        ConfigError,
        MapFileError,
        MapserverError,
        ProcessingError,
    )
    from mapserver.geometry import Pose2D, Transform2D
    from mapserver.maps import OccupancyMap, load_map
    from mapserver.pipeline import Outcome, process_bundle

_HOME = {
    "Config": "mapserver.config",
    "load_config": "mapserver.config",
    "BundleError": "mapserver.errors",
    "BundleIncomplete": "mapserver.errors",
    "ConfigError": "mapserver.errors",
    "MapFileError": "mapserver.errors",
    "MapserverError": "mapserver.errors",
    "ProcessingError": "mapserver.errors",
    "Pose2D": "mapserver.geometry",
    "Transform2D": "mapserver.geometry",
    "OccupancyMap": "mapserver.maps",
    "load_map": "mapserver.maps",
    "Outcome": "mapserver.pipeline",
    "process_bundle": "mapserver.pipeline",
}


def __getattr__(name: str) -> Any:
    if name in _HOME:
        return getattr(importlib.import_module(_HOME[name]), name)
    raise AttributeError(f"module 'mapserver' has no attribute {name!r}")


__all__ = [
    "BundleError",
    "BundleIncomplete",
    "Config",
    "ConfigError",
    "MapFileError",
    "MapserverError",
    "OccupancyMap",
    "Outcome",
    "Pose2D",
    "ProcessingError",
    "Transform2D",
    "load_config",
    "load_map",
    "process_bundle",
]
__version__ = "0.1.0"

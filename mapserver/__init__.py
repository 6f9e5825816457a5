"""mapserver: finds added and removed obstacles in robots' SLAM maps against the fleet's map."""

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

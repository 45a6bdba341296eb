"""Map input and output: ROS map_server maps, bare images, ``.npy`` arrays, ROS bags.

Everything gridmerge writes goes through :mod:`gridmerge.io.atomic`, so that an output is
either complete or absent.
"""

from .atomic import AtomicFiles, atomic_files, atomic_write
from .bags import BagTransform, bag_topics, child_frame_for, is_bag, read_bag_maps, write_bag, write_map_messages
from .images import MAX_PIXELS, encode_pgm, encode_png, image_size, read_image
from .map_server import (
    IMAGE_SUFFIXES,
    MAP_MODES,
    SAVE_MODES,
    YAML_SUFFIXES,
    grid_to_pixels,
    load_map,
    pixels_to_ros,
    save_map,
)

__all__ = [
    "load_map",
    "save_map",
    "pixels_to_ros",
    "grid_to_pixels",
    "read_image",
    "image_size",
    "encode_pgm",
    "encode_png",
    "atomic_write",
    "atomic_files",
    "AtomicFiles",
    "MAX_PIXELS",
    "MAP_MODES",
    "SAVE_MODES",
    "IMAGE_SUFFIXES",
    "YAML_SUFFIXES",
    "read_bag_maps",
    "write_bag",
    "write_map_messages",
    "is_bag",
    "bag_topics",
    "child_frame_for",
    "BagTransform",
]

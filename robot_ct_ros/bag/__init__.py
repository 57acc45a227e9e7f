"""Scan bags: the rosbag2/MCAP recording of a CT scan (contract: docs/bag-format.md).

``ScanBagWriter`` / ``write_scan`` write, ``read_scan`` reads (recovering damaged bags),
``robot_ct_ros.bag.format`` holds the topics, message layouts and unit conversions.
"""

from .format import FORMAT, ScanBagError, make_scan_info, scan_info_for
from .reader import RawBag, RawMessage, ScanData, read_raw_messages, read_scan, summarize
from .writer import ScanBagWriter, default_stamps, write_corrected_bag, write_scan

__all__ = [
    "FORMAT", "ScanBagError", "make_scan_info", "scan_info_for",
    "RawBag", "RawMessage", "ScanData", "read_raw_messages", "read_scan", "summarize",
    "ScanBagWriter", "default_stamps", "write_corrected_bag", "write_scan",
]

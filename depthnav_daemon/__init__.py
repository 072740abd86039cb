"""depthnav: depth sensor to laser scan, negative obstacles and mount pose for wheeled robots."""

__version__ = "0.1.0"

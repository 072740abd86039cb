"""Depth sensor drivers: one module per backend, chosen by a device spec string.

This package never imports depthnav_daemon.
"""

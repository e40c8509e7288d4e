"""Sensor models: how likely a set of ToF frames is for each of many candidate base poses."""

"""Pixel -> table-mm calibration from a plate of circles."""

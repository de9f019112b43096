"""Detections: what a camera saw, as image documents for the matcher.

* :mod:`~mapdb.detections.images` - image documents (JSON), read and checked against their schema;
* :mod:`~mapdb.detections.masks` - segmentation masks (PNG, GeoTIFF) to objects;
* :mod:`~mapdb.detections.coco` - COCO detections (polygons, RLE, boxes) to objects.
"""

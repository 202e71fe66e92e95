"""Gesture annotations: taxonomies as data, segment <-> frame-label conversion, VIA and JIGSAWS/COMPASS
importers and exporters, dataset statistics. Label sets are stored through ``midas_cli.session.labels``.
"""

"""Gesture recognition: dataset building, splits, networks (one file each), metrics and training runs."""

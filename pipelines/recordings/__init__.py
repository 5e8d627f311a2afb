"""Recordings of a predictions store for Foxglove, Rerun and ROS 2 (``radarseg export recording``)."""

"""Class colours of the recordings and the RA / RD label maps drawn as RGB images.

Class 0 (background) has no colour; the others take the project's figure colours (pipelines/figures.py) in turn.
A map is drawn with range increasing upwards (row 0 is the farthest range bin): labelled cells in their class's
colour, the others grey by their dB value (black without one). No class colour is grey, so a pixel's class reads
back exactly (:func:`classes_of_image`).
"""

from __future__ import annotations

import numpy as np

CLASS_RGB = ((255, 64, 64), (64, 192, 255), (255, 208, 0), (96, 255, 96), (200, 96, 255), (255, 128, 192))


def class_rgb(class_id: int) -> tuple[int, int, int]:
    """The RGB colour of a class (background: black)."""
    return (0, 0, 0) if class_id <= 0 else CLASS_RGB[(class_id - 1) % len(CLASS_RGB)]


def palette(num_classes: int) -> np.ndarray:
    """(num_classes, 3) uint8: row c is class c's colour."""
    return np.array([class_rgb(c) for c in range(num_classes)], np.uint8)


def label_image(labels: np.ndarray, db: np.ndarray | None, num_classes: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a label map (range, other axis) with range increasing upwards: class colours over the
    map's dB values in grey (scaled to its own range)."""
    if db is None:
        grey = np.zeros(labels.shape, np.uint8)
    else:
        low, high = float(db.min()), float(db.max())
        grey = ((db - low) * (255.0 / max(high - low, 1e-6))).astype(np.uint8)
    image = np.repeat(grey[..., None], 3, axis=2)
    classes = labels.astype(np.intp)
    coloured = classes > 0
    image[coloured] = palette(max(num_classes, int(classes.max()) + 1))[classes[coloured]]
    return np.ascontiguousarray(image[::-1])


def classes_of_image(image: np.ndarray, num_classes: int) -> np.ndarray:
    """The label map (range, other axis) an image of :func:`label_image` was drawn from."""
    rgb = image[::-1].astype(np.int32)
    labels = np.zeros(rgb.shape[:2], np.uint8)
    for class_id, colour in enumerate(palette(num_classes)[1:], start=1):
        labels[np.all(rgb == colour, axis=2)] = class_id
    return labels

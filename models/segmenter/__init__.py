"""Stage 2 of ERASE-Net: sparse segmenters labelling region-grown ROI voxels (SPEC section 7)."""

"""The radar-domain core: profiles, geometry, transforms, simulator, readers, region growing, metrics.

Everything else in radarseg imports this package; it imports none of them (numpy/scipy only).
"""

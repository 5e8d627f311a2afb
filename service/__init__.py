"""radarseg: service."""

"""radarseg: models."""

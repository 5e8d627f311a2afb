"""radarseg: radar/simulate."""

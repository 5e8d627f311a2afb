"""radarseg: radar/io."""

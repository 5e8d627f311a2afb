"""Built-in radar profiles as data files (TOML); see radar/profiles/files.py."""

"""Built-in radar profiles as data files (TOML); see radar/profile_files.py."""

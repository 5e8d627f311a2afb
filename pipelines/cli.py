"""The `radarseg` command line."""
def main(argv=None) -> int:
    raise SystemExit("radarseg: not implemented yet")

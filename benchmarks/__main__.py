"""``python -m benchmarks list | run NAME [ARGS...] | run --all``: see :mod:`benchmarks.harness`."""

from benchmarks.harness import main

raise SystemExit(main())

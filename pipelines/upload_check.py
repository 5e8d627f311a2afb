"""``radarseg upload-check [DIR]``: what ``ray job submit --working-dir DIR`` would upload, before Ray refuses it.

Ray's job submission zips the working directory (skipping what ``.gitignore`` and ``.rayignore`` list and the
``excludes`` of ``--runtime-env-json``) and PUTs it to the dashboard, which refuses a body of 100 MiB or more
with a bare HTTP 413 deep in a traceback. This check walks the directory with Ray's own ignore rules and fails
with one line naming the total and the largest files, so a run directory left in the tree is caught first.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from radar.errors import UserError

# The dashboard's aiohttp body limit for package uploads (ray_constants.DASHBOARD_CLIENT_MAX_SIZE).
UPLOAD_LIMIT_BYTES = 100 * 1024**2
MIB = 1024**2


class UploadTooLargeError(UserError):
    """The working directory would exceed the job-submission upload limit."""


def upload_files(root: str | Path, excludes: tuple[str, ...] = ()) -> list[tuple[Path, int]]:
    """``(path relative to root, bytes)`` of every file ``--working-dir root`` would upload, largest first."""
    from ray._private.ray_constants import get_runtime_env_default_excludes
    from ray._private.runtime_env.packaging import _dir_travel, _get_excludes

    root = Path(root).resolve()
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such directory (expected the --working-dir to check)")
    found: list[tuple[Path, int]] = []

    def visit(path: Path) -> None:
        if path.is_file() and not path.is_symlink():
            found.append((path.relative_to(root), path.stat().st_size))

    # The same walk as ray.job_submission's upload (packaging.get_uri_for_directory), .gitignore included, and with
    # Ray's own default excludes (.git, .venv, __pycache__: RAY_OVERRIDE_RUNTIME_ENV_DEFAULT_EXCLUDES changes them).
    everything = [*get_runtime_env_default_excludes(), *excludes]
    _dir_travel(root, [_get_excludes(root, everything)], visit, include_gitignore=True,
                logger=logging.getLogger(__name__))
    return sorted(found, key=lambda item: -item[1])


def check_upload(root: str | Path = ".", excludes: tuple[str, ...] = (),
                 limit_bytes: int = UPLOAD_LIMIT_BYTES) -> dict:
    """``{"files", "bytes", "limit_bytes"}``; raises :class:`UploadTooLargeError` (one line) over the limit.

    The total is of the files as they are, an upper bound of the zip Ray sends (checkpoints barely compress).
    """
    files = upload_files(root, excludes)
    total = sum(size for _, size in files)
    if total >= limit_bytes:
        largest = ", ".join(f"{path} {size / MIB:.1f} MiB" for path, size in files[:4])
        raise UploadTooLargeError(
            f"--working-dir {root} would upload {total / MIB:.1f} MiB in {len(files)} files, over Ray's "
            f"{limit_bytes / MIB:g} MiB job-submission limit (the dashboard answers HTTP 413); largest: {largest}; "
            f"list them in .gitignore or .rayignore, or pass --runtime-env-json "
            f"'{{\"excludes\": [\"{files[0][0].parts[0]}/\"]}}' to ray job submit")
    return {"files": len(files), "bytes": total, "limit_bytes": limit_bytes}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", nargs="?", default=".", help="the --working-dir to check (default: .)")
    parser.add_argument("--exclude", action="append", default=[], metavar="PATTERN",
                        help="a pattern of --runtime-env-json's excludes (gitignore syntax); repeat")
    parser.add_argument("--limit-mib", type=float, default=UPLOAD_LIMIT_BYTES / MIB,
                        help="upload limit in MiB (default: the Ray dashboard's 100)")


def run(args: argparse.Namespace) -> int:
    result = check_upload(args.dir, tuple(args.exclude), int(args.limit_mib * MIB))
    print(f"--working-dir {args.dir}: {result['files']} files, {result['bytes'] / MIB:.1f} MiB "
          f"(limit {result['limit_bytes'] / MIB:g} MiB): fits")
    return 0

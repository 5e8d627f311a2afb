"""Starting Ray, once for every job, test and benchmark: an embedded local Ray unless told otherwise."""

from __future__ import annotations

import logging
import os

from models.environment import environment

OBJECT_STORE_BYTES = 256 * 2**20  # embedded Ray: results are small summaries, the data goes to disk


def init_ray(address: str | None = None, *, num_cpus: int | None = None,
             object_store_bytes: int = OBJECT_STORE_BYTES) -> bool:
    """Connect to Ray unless already connected; returns True when this call connected (so the caller shuts down).

    ``address`` None and no ``RAY_ADDRESS``: a new embedded local Ray (never a cluster that happens
    to run on this machine) with ``num_cpus`` CPUs (None: the machine's), object store capped at
    ``object_store_bytes``, token auth and usage stats off. Under ``ray job submit`` the job's
    ``RAY_ADDRESS`` names the cluster.
    """
    import ray

    if ray.is_initialized():
        return False
    if address is None and not environment().ray_address:
        os.environ.setdefault("RAY_AUTH_MODE", "disabled")
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        ray.init(address="local", num_cpus=num_cpus, object_store_memory=object_store_bytes,
                 include_dashboard=False, logging_level=logging.WARNING)
    else:
        ray.init(address=address, logging_level=logging.WARNING)
    return True
